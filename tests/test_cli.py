"""The CLI end to end, as README's `make run` uses it (own Ray instance in a subprocess)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.integration
def test_collect_runs_the_pipeline_and_cleans_up(tmp_path):
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "rollout.cli",
            "collect",
            "--env",
            "unitysim:Basic",
            "--workers",
            "1",
            "--seconds",
            "6",
            "--horizon",
            "16",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=240,
        env={**__import__("os").environ, "UNITY_ROLLOUT_RUNTIME_DIR": str(tmp_path)},
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "agent steps" in result.stdout
    assert "'steps': {'Basic?team=0':" in result.stdout.replace("\n", "")
    assert "Basic?team=0: " in result.stdout  # mean return reported per behavior


def test_bad_build_path_is_a_one_line_error():
    result = subprocess.run(
        [sys.executable, "-m", "rollout.cli", "collect", "--env", "/no/such/Game"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert "no Unity build at '/no/such/Game'" in " ".join(result.stdout.split())


def test_restart_flags_as_mlagents_learn_names_them():
    result = subprocess.run(
        [sys.executable, "-m", "rollout.cli", "train", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    for flag in (
        "--max-lifetime-restarts",
        "--restarts-rate-limit-n",
        "--restarts-rate-limit-period-s",
        "--timeout-wait",
    ):
        assert flag in result.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "rollout.cli", "train", "--restarts-rate-limit-period-s", "0"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2
    assert "--restarts-rate-limit-period-s: positive, got 0" in " ".join(bad.stderr.split())
