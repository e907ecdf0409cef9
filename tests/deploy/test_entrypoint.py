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


def run(
    *args: str,
    env: dict[str, str] | None = None,
    prefix: tuple[str, ...] = (),
    script: Path = ENTRYPOINT,
):
    path = f"{Path(sys.executable).parent}:/usr/bin:/bin"  # unity-rollout, no xvfb-run
    return subprocess.run(
        [*prefix, "sh", str(script), *args],
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
    """Run as uid 65534 from a copy it can read: the checkout may sit where it cannot (a
    mode-0700 directory), as may pytest's tmp_path."""
    nobody = ("setpriv", "--reuid=65534", "--regid=65534", "--clear-groups")
    home, readable = tempfile.mkdtemp(dir="/tmp"), Path(tempfile.mkdtemp(dir="/tmp"))
    try:
        readable.chmod(0o755)
        script = Path(shutil.copy(ENTRYPOINT, readable / ENTRYPOINT.name))
        script.chmod(0o755)
        as_nobody = {"prefix": nobody, "script": script}
        result = run("sh", "-c", "echo $HOME", env={"HOME": "/"}, **as_nobody)
        assert (result.returncode, result.stdout) == (0, "/tmp\n"), result.stderr
        os.chown(home, 65534, 65534)
        kept = run("sh", "-c", "echo $HOME", env={"HOME": home}, **as_nobody)
        assert kept.stdout == f"{home}\n", kept.stderr  # a writable HOME is kept
    finally:
        shutil.rmtree(home)
        shutil.rmtree(readable)
