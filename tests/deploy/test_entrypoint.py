"""The image's entrypoint (scripts/docker-entrypoint.sh), run on this machine: arguments go
to unity-rollout, a program on PATH runs as written, xvfb-run without Xvfb gets one line,
and a uid without a writable HOME gets HOME=/tmp (Ray keeps its token there)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ENTRYPOINT = Path(__file__).resolve().parents[2] / "scripts/docker-entrypoint.sh"


def run(*args: str, env: dict[str, str] | None = None, prefix: tuple[str, ...] = ()):
    path = f"{Path(sys.executable).parent}:/usr/bin:/bin"  # unity-rollout, no xvfb-run
    return subprocess.run(
        [*prefix, "sh", str(ENTRYPOINT), *args],
        env={"PATH": path, "HOME": "/root", **(env or {})},
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_arguments_go_to_unity_rollout():
    result = run("train", "--help")
    assert result.returncode == 0, result.stderr
    assert "--max-seconds" in result.stdout


def test_a_program_on_path_runs_as_written():
    result = run("echo", "as", "written")
    assert (result.returncode, result.stdout) == (0, "as written\n")


@pytest.mark.skipif(shutil.which("xvfb-run") is not None, reason="this machine has xvfb-run")
def test_xvfb_run_without_xvfb_names_the_render_variant():
    result = run("xvfb-run", "-a", "unity-rollout", "train")
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "RENDER=1" in result.stderr, result.stderr


@pytest.mark.skipif(os.getuid() != 0 or not shutil.which("setpriv"), reason="needs root")
def test_an_uid_without_a_writable_home_gets_tmp():
    nobody = ("setpriv", "--reuid=65534", "--regid=65534", "--clear-groups")
    result = run("sh", "-c", "echo $HOME", env={"HOME": "/"}, prefix=nobody)
    assert (result.returncode, result.stdout) == (0, "/tmp\n"), result.stderr
    home = tempfile.mkdtemp(dir="/tmp")  # pytest's tmp_path is not reachable by uid 65534
    try:
        os.chown(home, 65534, 65534)
        kept = run("sh", "-c", "echo $HOME", env={"HOME": home}, prefix=nobody)
        assert kept.stdout == f"{home}\n"  # a writable HOME is kept
    finally:
        shutil.rmtree(home)
