# The two commands of README.md: `make run` (the main job) and `make test` (every test).
# Both create or reuse .venv through scripts/setup-venv.sh.
VENV ?= .venv
ARGS ?=

.PHONY: run test venv lint

venv:
	@scripts/setup-venv.sh

run: venv
	$(VENV)/bin/unity-rollout $(if $(ARGS),$(ARGS),train)

lint: venv
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

test: lint
	$(VENV)/bin/python -m pytest
