"""A unitysim player never outlives its trainer."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import psutil
import pytest

from tests.helpers import free_port, wait_gone

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]

TRAINER = """
import sys
import mlagents_compat
from mlagents_envs.environment import UnityEnvironment
env = UnityEnvironment(file_name=sys.argv[1], base_port=int(sys.argv[2]), no_graphics=True)
env.reset()
print(env._process.pid, flush=True)
sys.stdin.read()  # until killed (or the test's end)
"""


def test_player_exits_when_its_trainer_is_killed(builds):
    trainer = subprocess.Popen(
        [sys.executable, "-c", TRAINER, str(builds / "3DBall"), str(free_port())],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        player_pid = int(trainer.stdout.readline())
        assert psutil.pid_exists(player_pid)
        os.kill(trainer.pid, signal.SIGKILL)
        trainer.wait(10)
        assert wait_gone(player_pid), "player outlived its SIGKILLed trainer"
    finally:
        if trainer.poll() is None:
            trainer.kill()
            trainer.wait()


def test_close_ends_the_player_promptly(open_env):
    """Promptly: the player ends itself on the close message; mlagents kills one that has
    not ended within ``timeout_wait`` (then its code would be -9)."""
    with open_env("3DBall") as env:
        env.reset()
        player = env._process
        env.close()
        assert player.returncode == 0
        assert wait_gone(player.pid)


def test_launcher_execs_so_the_launched_pid_is_the_player(open_env):
    with open_env("Basic") as env:
        env.reset()
        command = " ".join(psutil.Process(env._process.pid).cmdline())
        assert "-m unitysim play --env Basic" in command


def test_player_without_port_explains_itself(builds):
    result = subprocess.run(
        [str(builds / "3DBall.x86_64")], capture_output=True, text=True, timeout=30
    )
    assert result.returncode == 2
    assert "--mlagents-port" in result.stderr
