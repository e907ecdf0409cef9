"""The image built and run for real: ``scripts/image-check.sh`` (``make image-check``) where
a container engine answers, skipped with the reason where none does.

It takes 5-6 minutes on 2 cores with a cold cache (a stand-in base from debootstrap, both
variants built), about 4 with images cached: more than the suite's budget leaves, so a
machine whose Docker daemon is not running skips it. ``UNITY_ROLLOUT_IMAGE_CHECK=1`` runs it
anyway (the check then starts a private daemon as root)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import psutil
import pytest

ROOT = Path(__file__).resolve().parents[2]
STEPS = (
    "--help: ok",
    "a root-owned results dir: one line, exit 2",
    "train --max-seconds 60: exit 0, mean reward",
    "docker stop: graceful in",
    "--user 12345:12345: exit 0",
    "xvfb-run in the headless image: one line naming the render variant",
    "render variant: xvfb-run -a unity-rollout train: exit 0",
    "an unreachable torch CPU index: the build stops with one line",
    "image-check: passed",
)


def engine_problem() -> str | None:
    if os.environ.get("UNITY_ROLLOUT_IMAGE_CHECK") == "1":
        return None
    if shutil.which("docker") is None:
        return "no container engine (no docker client): run `make image-check` where one is"
    answer = subprocess.run(["docker", "info"], capture_output=True, timeout=60)
    if answer.returncode != 0:
        return (
            "no container engine answers `docker info`; `make image-check` (or "
            "UNITY_ROLLOUT_IMAGE_CHECK=1) starts its own: 5-6 min"
        )
    return None


@pytest.mark.integration
@pytest.mark.timeout(2400)
def test_the_image_builds_trains_stops_and_runs_as_any_uid(tmp_path):
    problem = engine_problem()
    if problem:
        pytest.skip(problem)
    cache = os.environ.get("IMAGE_CHECK_DIR") or str(
        Path.home() / ".cache/unity-rollout-image-check"
    )
    result = subprocess.run(
        ["scripts/image-check.sh"],
        cwd=ROOT,
        env={**os.environ, "IMAGE_CHECK_DIR": cache},
        capture_output=True,
        text=True,
        timeout=2300,
    )
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-4000:]
    for step in STEPS:
        assert step in output, f"{step!r} missing:\n{output[-4000:]}"
    # everything it started is gone: its private daemon, the wheel server
    left = [
        p.info["pid"]
        for p in psutil.process_iter(["pid", "cmdline"])
        if any(cache in part for part in (p.info["cmdline"] or []))
    ]
    assert left == [], f"processes of the check still running: {left}"
