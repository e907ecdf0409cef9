# unity-rollout: Ray rollout workers + central learner, one headless Unity instance per CPU.
#
#   docker build -t unity-rollout:0.1.0 .
#   docker run --rm --shm-size=2g -v "$PWD/results:/workspace/results" unity-rollout:0.1.0
#       -> `unity-rollout train` on unitysim 3DBall in local 2-core mode (no build needed)
#   docker run --rm --shm-size=2g -v /path/to/LinuxBuild:/builds:ro \
#       -v "$PWD/results:/workspace/results" unity-rollout:0.1.0 train --env /builds/Game.x86_64
#
# The same image is the Ray node image of deploy/ (cluster launcher, KubeRay); see
# deploy/README.md. Python packages come only from scripts/setup-venv.sh with
# constraints.txt, exactly as `make run` / `make test` install them (tests/deploy checks it).
FROM python:3.11-slim-bookworm

# Runtime libraries of a headless Linux Unity player (-batchmode -nographics): Unity links
# libGL/libGLU and a few X11 client libraries even when it renders nothing, and loads
# libasound at start-up. Xvfb (with xauth for xvfb-run) is only for builds with camera or
# render-texture observations, which need a display: `xvfb-run -a unity-rollout train ...`.
# tini reaps the Unity players as PID 1; wget serves KubeRay's probes; procps gives `ps`.
# Versions follow the pinned Debian release of the base image (no apt pins: the image
# registry and Debian mirrors are not reachable where this file is tested).
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        ca-certificates \
        libasound2 \
        libgl1 \
        libglu1-mesa \
        libxcursor1 \
        libxext6 \
        libxi6 \
        libxinerama1 \
        libxrandr2 \
        libxrender1 \
        procps \
        tini \
        wget \
        xauth \
        xvfb \
    && rm -rf /var/lib/apt/lists/*

SHELL ["/bin/bash", "-o", "pipefail", "-c"]

# Non-root: uid/gid 1000 (the KubeRay manifests run as the same ids).
RUN groupadd --gid 1000 rollout \
    && useradd --uid 1000 --gid 1000 --create-home --shell /bin/bash rollout

# Everything the package needs at install and run time (config/: the shipped trainer configs).
WORKDIR /opt/unity-rollout
COPY pyproject.toml setup.py constraints.txt README.md ./
COPY scripts/setup-venv.sh scripts/setup-venv.sh
COPY rollout/ rollout/
COPY learners/ learners/
COPY unitysim/ unitysim/
COPY config/ config/

# The README's installer, unchanged: pinned by constraints.txt, mlagents-envs with --no-deps.
# PIP_EXTRA_INDEX_URL: torch's CPU wheels (2.13.0+cpu satisfies the torch==2.13.0 pin), so
# the image does not pull several GB of CUDA libraries. EXTRAS= (empty): runtime packages
# only, no test tools.
ARG PIP_EXTRA_INDEX_URL=https://download.pytorch.org/whl/cpu
# gcc and libc6-dev build unitysim's C 3DBall physics (setup.py) and leave in the same
# layer; the import after the purge fails the build if the extension is missing (setup.py
# would only warn). The profile.d line is literal on purpose: login shells (KubeRay's
# bash -lc) expand it.
# hadolint ignore=SC2016,DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && PYTHON=python3.11 VENV=/opt/venv EXTRAS= PIP_NO_CACHE_DIR=1 scripts/setup-venv.sh \
    && apt-get purge -y --auto-remove gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/* \
    && /opt/venv/bin/python -c "import unitysim.envs._ball3d" \
    && /opt/venv/bin/unity-rollout doctor \
    && printf 'export VIRTUAL_ENV=/opt/venv\nexport PATH=/opt/venv/bin:$PATH\n' \
        > /etc/profile.d/unity-rollout.sh

ENV VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    RAY_AUTH_MODE=token

# /builds: mount a Linux Unity build here (read-only is fine), e.g. /builds/Game.x86_64.
# /workspace/results: every run's TensorBoard events, checkpoints and summary.json.
RUN mkdir -p /builds /workspace/results \
    && chown rollout:rollout /workspace /workspace/results
VOLUME ["/workspace/results"]
WORKDIR /workspace
USER 1000:1000

# Liveness of the installed stack: the interpreter, mlagents-envs through rollout.compat,
# protobuf's backend (well under a second).
HEALTHCHECK --interval=60s --timeout=20s --start-period=20s --retries=3 \
    CMD ["unity-rollout", "doctor"]

ENTRYPOINT ["tini", "--", "unity-rollout"]
CMD ["train"]
