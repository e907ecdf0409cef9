"""rollout.environment.unity: a leased loopback-only port, a player tied to its owner, clear errors
for bad builds, restarts on a fresh port after a crash."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import grpc
import numpy as np
import psutil
import pytest

from rollout.environment.ports import PortAllocator, PortRange
from rollout.environment.restarts import RestartPolicy
from rollout.environment.unity import (
    RECOVERABLE,
    UnityConfig,
    UnityError,
    UnityInstance,
    UnityStartError,
    resolve_build,
)
from tests.helpers import leak_checked_allocator, wait_gone

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]
BALL = "3DBall?team=0"


@pytest.fixture
def allocator(tmp_path):
    with leak_checked_allocator(tmp_path, 24000, 24099, quarantine_s=60) as allocator:
        yield allocator


def test_instance_runs_on_a_confirmed_loopback_port(allocator):
    with UnityInstance(UnityConfig("unitysim:3DBall", seed=1), allocator) as unity:
        port = unity.port
        assert allocator.leases()[port]["bound"] is True
        listening = [
            c.laddr
            for c in psutil.Process().net_connections("tcp")
            if c.status == psutil.CONN_LISTEN and c.laddr.port == port
        ]
        loopback = {"127.0.0.1", "::ffff:127.0.0.1"}  # gRPC may use a v4-mapped v6 socket
        assert listening and all(address.ip in loopback for address in listening)
        # gRPC's default SO_REUSEPORT cannot silently share our port.
        intruder = grpc.server(None, options=(("grpc.so_reuseport", 1),))
        try:
            with pytest.raises(RuntimeError):
                if intruder.add_insecure_port(f"[::]:{port}") == 0:
                    raise RuntimeError("bind failed")
        finally:
            intruder.stop(None)
        unity.reset()
        unity.step()
        decisions, _ = unity.get_steps(BALL)
        assert len(decisions) == 12
        pid = unity.player_pid
    assert wait_gone(pid)
    assert port in allocator.quarantined()


def test_missing_and_unexecutable_builds_fail_at_once(tmp_path):
    with pytest.raises(UnityError, match="no Unity build at"):
        resolve_build(str(tmp_path / "Nothing"))
    build = tmp_path / "Game.x86_64"
    build.write_text("#!/bin/sh\n")
    build.chmod(0o644)
    with pytest.raises(UnityError, match="is not executable: run chmod"):
        resolve_build(str(tmp_path / "Game"))
    with pytest.raises(UnityError, match="unknown unitysim environment 'Nope'"):
        resolve_build("unitysim:Nope")


def test_incompatible_version_is_a_clear_error(allocator):
    config = UnityConfig(
        "unitysim:3DBall", additional_args=("--sim-communication-version", "2.0.0")
    )
    with pytest.raises(UnityError, match="communication API version is not compatible"):
        UnityInstance(config, allocator).start()


def test_killed_player_is_restarted_on_a_fresh_port(allocator):
    with UnityInstance(
        UnityConfig("unitysim:3DBall", restarts=RestartPolicy(backoff_s=0.0)), allocator
    ) as unity:
        unity.reset()
        first_port, first_pid = unity.port, unity.player_pid
        os.kill(first_pid, signal.SIGKILL)
        with pytest.raises(Exception) as failure:
            for _ in range(50):
                unity.step()
        assert isinstance(failure.value, RECOVERABLE)
        unity.restart(str(failure.value))
        unity.reset()
        unity.step()
        assert unity.restarts == 1
        assert unity.port != first_port
        assert first_port in allocator.quarantined()
        assert len(unity.get_steps(BALL)[0]) == 12


LIFETIME_1 = RestartPolicy(max_lifetime_restarts=1, backoff_s=0.0)


def test_restart_budget_is_enforced(allocator):
    unity = UnityInstance(UnityConfig("unitysim:Basic", restarts=LIFETIME_1), allocator)
    unity.start()
    try:
        unity.restart("first")
        with pytest.raises(UnityError, match="lifetime limit of 1 restarts reached"):
            unity.restart("second")
    finally:
        unity.close()


OWNER = """
import sys
from rollout.environment.ports import PortAllocator, PortRange
from rollout.environment.unity import UnityConfig, UnityInstance
allocator = PortAllocator(PortRange(24100, 24199), sys.argv[1])
config = UnityConfig("unitysim:3DBall", additional_args=("--no-parent-watch",))
unity = UnityInstance(config, allocator)
unity.start()
print(unity.player_pid, flush=True)
sys.stdin.read()  # until killed (or the test's end)
"""


def test_player_dies_with_its_sigkilled_owner(tmp_path):
    """The player ignores its own parent watch here: only the launch guard can end it."""
    owner = subprocess.Popen(
        [sys.executable, "-c", OWNER, str(tmp_path)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        player = int(owner.stdout.readline())
        assert "--no-parent-watch" in psutil.Process(player).cmdline()
        owner.send_signal(signal.SIGKILL)
        owner.wait(10)
        assert wait_gone(player), "the player outlived its SIGKILLed owner"
    finally:
        if owner.poll() is None:
            owner.kill()
            owner.wait()
    # The dead owner's lease is reclaimed by the next registry access.
    assert PortAllocator(PortRange(24100, 24199), tmp_path).leases() == {}


def test_stats_are_forwarded(allocator):
    with UnityInstance(UnityConfig("unitysim:Echo", seed=2), allocator) as unity:
        unity.reset()
        for _ in range(60):
            for behavior in unity.behavior_specs:
                decisions, _ = unity.get_steps(behavior)
                spec = unity.behavior_specs[behavior]
                unity.set_actions(behavior, spec.action_spec.empty_action(len(decisions)))
            unity.step()
        stats = unity.drain_stats()
    assert stats["Echo/Episodes Ended"] and all(m == 2 for _, m in stats["Echo/Episodes Ended"])
    assert np.sum([v for v, _ in stats["Echo/Episodes Ended"]]) > 0


def test_fast_step_input_equals_mlagents_original():
    """GuardedUnityEnvironment._generate_step_input builds exactly mlagents' message."""
    from mlagents_envs.base_env import ActionTuple
    from mlagents_envs.environment import UnityEnvironment
    from mlagents_envs.side_channel.side_channel_manager import SideChannelManager

    from rollout.environment.unity import GuardedUnityEnvironment

    rng = np.random.default_rng(0)
    env = object.__new__(GuardedUnityEnvironment)
    env._env_state = {"A?team=0": ([0] * 5, []), "B?team=0": ([0] * 3, []), "C?team=0": ([], [])}
    env._side_channel_manager = SideChannelManager([])
    actions = {
        "A?team=0": ActionTuple(continuous=rng.normal(size=(5, 2)).astype(np.float32)),
        "B?team=0": ActionTuple(
            continuous=rng.normal(size=(3, 1)).astype(np.float32),
            discrete=rng.integers(0, 3, size=(3, 2)).astype(np.int32),
        ),
        "C?team=0": ActionTuple(discrete=np.zeros((0, 1), np.int32)),
    }
    original = UnityEnvironment._generate_step_input(env, actions)
    fast = env._generate_step_input(actions)
    assert fast == original
    assert fast.SerializeToString(deterministic=True) == original.SerializeToString(
        deterministic=True
    )


@pytest.mark.parametrize(
    ("flags", "timeout_wait"),
    [
        (("--sim-crash-after", "3"), 20),
        (("--sim-status-after", "3"), 20),
        (("--sim-oversize-after", "3"), 20),
        (("--sim-nan-after", "3"), 20),
        (
            ("--sim-hang-after", "3"),
            15,
        ),  # a hang is found after this; a start must fit in it (8 s failed under a loaded suite)
    ],
    ids=["exit", "status-500", "oversized", "nan", "hang"],
)
def test_each_failure_restarts_on_a_fresh_port_until_the_budget_is_spent(
    allocator, flags, timeout_wait
):
    """The fault repeats in every restarted player, so the budget runs out."""
    from learners.acting.factory import actor_factory
    from rollout.collecting.collector import Collector

    config = UnityConfig(
        "unitysim:3DBall",
        additional_args=flags,
        timeout_wait=timeout_wait,
        restarts=RestartPolicy(max_lifetime_restarts=2, backoff_s=0.0),
    )
    collector = Collector(config, actor_factory, horizon=4, allocator=allocator)
    try:
        with pytest.raises(UnityError, match="lifetime limit of 2 restarts reached"):
            for _ in range(50):
                collector.collect()
        assert collector.snapshot().restarts == 2
        # The first player and both restarts each ran on their own port, now quarantined.
        assert len(allocator.quarantined()) == 3
    finally:
        collector.close()


def test_editor_mode_leases_5004_and_plays(allocator):
    editor = subprocess.Popen(
        [sys.executable, "-m", "unitysim", "editor", "--env", "3DBall"],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        with UnityInstance(UnityConfig(None), allocator) as unity:
            assert unity.port == 5004 and unity.player_pid is None
            unity.reset()
            unity.step()
            assert len(unity.get_steps(BALL)[0]) == 12
        assert editor.wait(timeout=15) == 0  # the editor session ends with the trainer
    finally:
        if editor.poll() is None:
            editor.kill()
            editor.wait()


# mlagents passes ``-logFile <folder>/Player-0.log``; a player that got that far wrote it
WRITES_ITS_LOG = 'while [ "$1" != -logFile ]; do shift; done; echo started > "$2"; '


# an exit is seen at once, so its wait may be long; a loaded machine may take seconds to
# run even these scripts (under the suite, 2 s failed for an exit and a log written, and
# once 15 s for a log written, on a slower 2-core machine)
@pytest.mark.parametrize(
    ("script", "wait", "message", "log"),
    [
        ("exit 0", 30, "the player exited with code 0 before it connected", False),
        (WRITES_ITS_LOG + "exit 0", 30, "the player exited with code 0 before it", True),
        ("exec sleep 600", 2, "did not connect within timeout_wait (2 s)", False),
        (WRITES_ITS_LOG + "exec sleep 600", 40, "did not connect within timeout_wait (40 s)", True),
    ],
    ids=["exits", "exits-logged", "silent", "silent-logged"],
)
def test_a_build_that_never_connects_is_one_line_naming_its_log(
    allocator, tmp_path, script, wait, message, log
):
    """The player's log is named when there is one, else the line says it wrote none."""
    build = tmp_path / "Game.x86_64"
    build.write_text(f"#!/bin/sh\n{script}\n")
    build.chmod(0o755)
    (tmp_path / "logs").mkdir()
    config = UnityConfig(str(build), timeout_wait=wait, log_folder=str(tmp_path / "logs"))
    with pytest.raises(UnityStartError) as error:
        UnityInstance(config, allocator).start()
    assert message in str(error.value) and "\n" not in str(error.value)
    ending = f"its log: {tmp_path}/logs/Player-0.log" if log else "it wrote no log"
    assert str(error.value).endswith(ending)


def test_a_build_path_with_spaces_launches(allocator, tmp_path):
    from unitysim.launcher import build as build_launchers

    (launcher,) = build_launchers(tmp_path / "My Game" / "Build 1", ["Basic"])
    with UnityInstance(UnityConfig(str(launcher)), allocator) as unity:
        unity.reset()
        unity.step()
        assert len(unity.get_steps("Basic?team=0")[0]) == 1
