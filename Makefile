# The two commands of README.md: `make run` (the main job) and `make test` (every test).
# Both create or reuse .venv through scripts/setup-venv.sh.
VENV ?= .venv
ARGS ?=

.PHONY: run test venv lint image-check

venv:
	@scripts/setup-venv.sh

run: venv
	$(VENV)/bin/unity-rollout $(if $(ARGS),$(ARGS),train)

lint: venv
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# Three pytest workers (pytest-xdist) on 2 cores, each module's tests on one of them (its
# fixtures made once): the suite mostly waits on players, Ray and sockets (two workers kept
# the cores 44% busy, 17 min; three took 13.7 min).
test: lint
	$(VENV)/bin/python -m pytest -n 3 --dist loadscope

# Build the Dockerfile and run the image as a user would (root or a reachable Docker daemon;
# ~10 min the first time, see scripts/image-check.sh).
image-check:
	scripts/image-check.sh
