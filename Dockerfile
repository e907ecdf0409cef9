# unity-rollout: Ray rollout workers + central learner, one headless Unity instance per CPU.
#
#   docker build -t unity-rollout:0.1.0 .
#   mkdir -p results && sudo chown 1000 results   # the container writes as uid 1000
#   docker run --rm --shm-size=2g -v "$PWD/results:/workspace/results" unity-rollout:0.1.0
#       -> `unity-rollout train` on unitysim 3DBall in local 2-core mode (no build needed)
#   docker run --rm --shm-size=2g -v /path/to/LinuxBuild:/builds:ro \
#       -v "$PWD/results:/workspace/results" unity-rollout:0.1.0 train --env /builds/Game.x86_64
#   docker build --build-arg TORCH=cu130 -t unity-rollout:0.1.0-gpu .
#       -> the GPU learner's image: `docker run --gpus all ... train --device cuda`
#
# Build arguments:
#   RENDER=1   the render variant: Xvfb and mesa's software GL (~300 MB), for builds with
#              camera or render-texture observations: `docker run ... IMAGE xvfb-run -a
#              unity-rollout train ...`. Headless builds (-nographics) need neither.
#   TORCH      which build of torch (scripts/check-torch-index.py; anything else stops the
#              build with one line naming these):
#                cpu    (default) CPU only, from torch's CPU index;
#                cu126, cu130, cu132   CUDA 12.6 / 13.0 / 13.2 from torch's index of that
#                       build; the wheels bring their CUDA runtime (nvidia-* packages, several
#                       GB), so the base stays the same; the host needs only the NVIDIA driver
#                       and Container Toolkit (deploy/README.md, "GPU learner");
#                any    whichever build pip finds (the CPU index first), nothing checked.
#              The build stops with a one-line error when the chosen build's wheel is not on
#              the index, instead of pip silently taking another build.
#   EXTRAS=tune  with Ray Tune, for `unity-rollout tune` (pandas and pyarrow, ~250 MB more).
#   PIP_EXTRA_INDEX_URL   torch's index for TORCH, unless set (a mirror of it).
#   BASE       the Python base image (scripts/image-check.sh passes a local stand-in when
#              no image registry is reachable).
#
# The same image is the Ray node image of deploy/ (cluster launcher, KubeRay); see
# deploy/README.md. Python packages come only from scripts/setup-venv.sh with
# constraints.txt, exactly as `make run` / `make test` install them (tests/deploy checks it).
# `make image-check` builds this file and runs the image as a user would.
ARG BASE=python:3.11-slim-bookworm

# ---- build: the virtual environment. The C compiler (unitysim's 3DBall physics) and
# what the runtime never imports stay in this stage.
FROM ${BASE} AS build
SHELL ["/bin/bash", "-o", "pipefail", "-c"]
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/* /var/cache/apt/*.bin

# Everything the package needs at install and run time (config/: the shipped trainer configs).
WORKDIR /opt/unity-rollout
COPY pyproject.toml setup.py constraints.txt README.md ./
COPY scripts/setup-venv.sh scripts/check-torch-index.py scripts/docker-entrypoint.sh scripts/
COPY batches/ batches/
COPY demonstrations/ demonstrations/
COPY driver/ driver/
COPY gymnasium_adapters/ gymnasium_adapters/
COPY learners/ learners/
COPY mlagents_compat/ mlagents_compat/
COPY rollout/ rollout/
COPY torchrl_adapters/ torchrl_adapters/
COPY unitysim/ unitysim/
COPY config/ config/

# The README's installer, unchanged: pinned by constraints.txt, mlagents-envs with --no-deps.
# PIP_EXTRA_INDEX_URL: the index of TORCH's build (2.13.0+cpu or 2.13.0+cu130 satisfies the
# torch==2.13.0 pin), so the CPU image does not pull several GB of CUDA libraries and the
# GPU image gets the CUDA build it names. The first two steps only choose the index (no
# network; tests/deploy/test_dockerfile.py runs them as written). EXTRAS (empty by
# default): runtime packages only, no test tools; `tune` adds Ray Tune. The import fails the build if the C extension is missing
# (setup.py would only warn). Then out go torch's C++ test programs, headers (for compiling
# extensions) and Ray's Java workers: nothing here imports or runs them.
ARG TORCH=cpu
ARG EXTRAS=
ARG PIP_EXTRA_INDEX_URL=
RUN PIP_EXTRA_INDEX_URL=$(python3.11 scripts/check-torch-index.py --index-for "$TORCH" "$PIP_EXTRA_INDEX_URL") \
    && export PIP_EXTRA_INDEX_URL \
    && python3.11 scripts/check-torch-index.py --torch "$TORCH" "$PIP_EXTRA_INDEX_URL" \
    && PYTHON=python3.11 VENV=/opt/venv EXTRAS="$EXTRAS" PIP_NO_CACHE_DIR=1 scripts/setup-venv.sh \
    && /opt/venv/bin/python -c "import unitysim.envs._ball3d" \
    && /opt/venv/bin/python scripts/check-torch-index.py --torch "$TORCH" --installed \
    && site=/opt/venv/lib/python3.11/site-packages \
    && rm -rf "$site/torch/test" "$site/torch/include" "$site/ray/jars" \
    && find "$site/torch/bin" -mindepth 1 -maxdepth 1 ! -name torch_shm_manager -exec rm -rf {} + \
    && /opt/venv/bin/unity-rollout doctor

# ---- the image
FROM ${BASE}
SHELL ["/bin/bash", "-o", "pipefail", "-c"]

# Runtime libraries of a headless Linux Unity player (-batchmode -nographics): libasound
# and a few X11 client libraries it loads at start-up. tini reaps the Unity players as
# PID 1; wget serves KubeRay's probes; procps gives `ps`. RENDER=1 adds Xvfb (with xauth
# for xvfb-run) and GL/GLU (mesa's software renderer) for builds that render.
# Versions follow the pinned Debian release of the base image (no apt pins: the image
# registry and Debian mirrors are not reachable where this file is tested).
ARG RENDER=
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        ca-certificates \
        libasound2 \
        libxcursor1 \
        libxext6 \
        libxi6 \
        libxinerama1 \
        libxrandr2 \
        libxrender1 \
        procps \
        tini \
        wget \
        ${RENDER:+libgl1 libglu1-mesa xauth xvfb} \
    && rm -rf /var/lib/apt/lists/* /var/cache/apt/*.bin

# Non-root: uid/gid 1000 (the KubeRay manifests run as the same ids). Any other uid works
# too (docker run --user, OpenShift): the entrypoint and login shells give it HOME=/tmp.
RUN groupadd --gid 1000 rollout \
    && useradd --uid 1000 --gid 1000 --create-home --shell /bin/bash rollout

COPY --from=build /opt/venv /opt/venv
COPY --from=build /opt/unity-rollout /opt/unity-rollout

# The profile.d lines are literal on purpose: login shells (KubeRay's bash -lc) expand them.
# hadolint ignore=SC2016
RUN printf '%s\n' 'export VIRTUAL_ENV=/opt/venv' 'export PATH=/opt/venv/bin:$PATH' \
        '[ -w "${HOME:-/}" ] || export HOME=/tmp' > /etc/profile.d/unity-rollout.sh

# NVIDIA_DRIVER_CAPABILITIES: what the NVIDIA Container Toolkit mounts from the host's
# driver when a GPU is given (docker run --gpus, Kubernetes' nvidia.com/gpu): CUDA (compute)
# and NVML (utility, how Ray finds the GPU). As in NVIDIA's CUDA images; without a GPU it
# does nothing, so the CPU image carries it too.
ENV VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    RAY_AUTH_MODE=token \
    NVIDIA_DRIVER_CAPABILITIES=compute,utility

# /builds: mount a Linux Unity build here (read-only is fine), e.g. /builds/Game.x86_64.
# /workspace/results: every run's TensorBoard events, checkpoints and summary.json.
RUN mkdir -p /builds /workspace/results \
    && chown rollout:rollout /workspace /workspace/results \
    && chmod 1777 /workspace/results
VOLUME ["/workspace/results"]
WORKDIR /workspace
USER 1000:1000

# Liveness of the installed stack: the interpreter, mlagents-envs through mlagents_compat,
# protobuf's backend (well under a second).
HEALTHCHECK --interval=60s --timeout=20s --start-period=20s --retries=3 \
    CMD ["unity-rollout", "doctor"]

ENTRYPOINT ["tini", "--", "/opt/unity-rollout/scripts/docker-entrypoint.sh"]
CMD ["train"]
