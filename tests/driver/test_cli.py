"""The CLI end to end, as README's `make run` uses it (own Ray instance in a subprocess)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def cli(*args: str, timeout: float = 120, **env: str) -> subprocess.CompletedProcess:
    """``unity-rollout ARGS`` from the checkout, as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "driver.cli", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, **env},
    )


@pytest.mark.integration
def test_collect_runs_the_pipeline_and_cleans_up(tmp_path):
    result = cli(
        *("collect", "--env", "unitysim:Basic", "--workers", "1", "--seconds", "6"),
        *("--horizon", "16"),
        timeout=240,
        UNITY_ROLLOUT_RUNTIME_DIR=str(tmp_path),
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "agent steps" in result.stdout
    assert "'steps': {'Basic?team=0':" in result.stdout.replace("\n", "")
    assert "Basic?team=0: " in result.stdout  # mean return reported per behavior


def test_bad_build_path_is_a_one_line_error():
    result = cli("collect", "--env", "/no/such/Game")
    assert result.returncode == 2
    assert "no Unity build at '/no/such/Game'" in " ".join(result.stdout.split())


def test_restart_flags_as_mlagents_learn_names_them():
    result = cli("train", "--help")
    for flag in (
        "--max-lifetime-restarts",
        "--restarts-rate-limit-n",
        "--restarts-rate-limit-period-s",
        "--timeout-wait",
    ):
        assert flag in result.stdout
    bad = cli("train", "--restarts-rate-limit-period-s", "0")
    assert bad.returncode == 2
    assert "--restarts-rate-limit-period-s: positive, got 0" in " ".join(bad.stderr.split())
