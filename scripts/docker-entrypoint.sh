#!/bin/sh
# The image's entrypoint, under tini (PID 1, which reaps the Unity players).
#   docker run IMAGE [ARGS]          -> unity-rollout ARGS (default: train)
#   docker run IMAGE COMMAND [ARGS]  -> COMMAND as written, when it is a program on PATH:
#                                       xvfb-run -a unity-rollout train ... (render variant), bash
set -e
# Any uid (docker run --user, OpenShift's random uids) has a writable HOME: Ray keeps its
# token under it, and an uid with no passwd entry gets HOME=/ from Docker.
if [ ! -w "${HOME:-/}" ]; then
    export HOME=/tmp
fi
if [ "$#" -gt 0 ] && [ "$1" = xvfb-run ] && ! command -v xvfb-run >/dev/null 2>&1; then
    echo "error: xvfb-run is only in the render variant of the image:" \
        "docker build --build-arg RENDER=1 -t unity-rollout:0.1.0-render ." >&2
    exit 2
fi
if [ "$#" -gt 0 ] && [ "${1#-}" = "$1" ] && command -v "$1" >/dev/null 2>&1; then
    exec "$@"
fi
exec unity-rollout "$@"
