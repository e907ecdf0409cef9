"""Small helpers shared by the tests that start processes and read their segments."""

from __future__ import annotations

import contextlib
import itertools
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import psutil
import torch
from tensordict import TensorDict

from batches import keys
from rollout.environment.ports import PortAllocator, PortRange, ephemeral_range
from tests.waiting import poll_until

# Above the kernel's ephemeral range (32768-60999 by default): no outgoing connection (a
# player's, Ray's) can take one of these between the check and the test's bind, as it can
# an OS-chosen port; and outside the allocator's default range (below the ephemeral one).
# Handed out in turn from a random start, never twice in a session.
TEST_PORTS = range(ephemeral_range()[1] + 1, 65536)
_turn = itertools.count(random.randrange(len(TEST_PORTS)))


def _bindable(port: int) -> bool:
    """Free on every address a trainer binds (mlagents binds [::], which covers 0.0.0.0)."""
    for family, host in ((socket.AF_INET, "0.0.0.0"), (socket.AF_INET6, "::")):
        try:
            with socket.socket(family, socket.SOCK_STREAM) as probe:
                probe.bind((host, port))
        except OSError:
            if family == socket.AF_INET or socket.has_ipv6:
                return False
    return True


def free_port() -> int:
    """A port nothing listens on or connects from (for tests that bypass the allocator)."""
    for _ in range(len(TEST_PORTS)):
        port = TEST_PORTS[next(_turn) % len(TEST_PORTS)]
        if _bindable(port):
            return port
    raise RuntimeError(f"no free port in {TEST_PORTS}")


def free_run(count: int = 8) -> tuple[int, int]:
    """First and last of ``count`` ports from a free one: the allocator skips any of them
    another program takes meanwhile, which a one-port range cannot survive."""
    for _ in range(len(TEST_PORTS)):
        port = free_port()
        if port + count - 1 <= TEST_PORTS[-1]:
            return port, port + count - 1
    raise RuntimeError(f"no run of {count} ports in {TEST_PORTS}")


def gone(pid: int) -> bool:
    """Whether process ``pid`` has ended (a zombie counts: it runs nothing)."""
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def wait_gone(pid: int, seconds: float = 30) -> bool:
    """Whether process ``pid`` is gone (or a zombie) within ``seconds`` (a safety stop)."""
    return poll_until(lambda: gone(pid), seconds)


@contextlib.contextmanager
def leak_checked_allocator(
    tmp_path: Path, first: int, last: int, **kwargs: float
) -> Iterator[PortAllocator]:
    """A port allocator with its own range and registry that fails the test if a port is
    still leased at the end (every test's ports must go back)."""
    allocator = PortAllocator(PortRange(first, last), tmp_path / "ports", **kwargs)
    yield allocator
    assert allocator.leases() == {}, "a test left a port leased"


def trajectories(segment: TensorDict) -> list[slice]:
    """The packed trajectories of a segment: each ends with ``done``, the last one too."""
    done = segment[keys.NEXT, keys.DONE][:, 0]
    ends = torch.nonzero(done)[:, 0].tolist()
    assert ends and ends[-1] == len(done) - 1, "every trajectory ends with done"
    starts = [0] + [end + 1 for end in ends[:-1]]
    return [slice(start, end + 1) for start, end in zip(starts, ends, strict=True)]


def train_in_process(
    config: Path,
    env: str,
    behavior: str,
    *,
    step_budget: int,
    goal: float,
    safety_stop_s: float,
    ports: PortRange,
    registry: Path,
    chunk: int = 768,
    min_episodes: int = 10,
    seed: int = 0,
) -> tuple[float, list[tuple[int, int, float]]]:
    """Train one collector and the learner in this process until the mean return over
    ``min_episodes`` or more recent episodes reaches ``goal`` or ``step_budget`` agent
    steps are spent; (best mean return, history of (steps, episodes, best)). Each collect
    asks no more than the learner's next on-policy update wants, as the service does. The
    wall-time stop only ends a hung run: a busy machine is slower, same steps."""
    from learners.host.learner import CentralLearner
    from learners.trainer_config.parse import load_config
    from rollout.collecting.collector import Collector
    from rollout.environment.unity import UnityConfig

    torch.manual_seed(seed)
    learner = CentralLearner(load_config(config), seed=seed)
    collector = Collector(
        UnityConfig(env, seed=seed + 1),
        learner.factory,
        horizon=learner.config.for_behavior(behavior).time_horizon,
        allocator=PortAllocator(ports, registry),
    )
    started, best, history = time.monotonic(), float("-inf"), []
    _, wanted = learner.submit([])
    try:
        while collector.metrics.agent_steps < step_budget and best < goal:
            assert time.monotonic() - started < safety_stop_s, f"safety stop: {history}"
            ask = chunk if wanted is None else min(chunk, wanted)
            version, wanted = learner.submit(collector.collect(min_steps=ask))
            if version > collector.version:
                collector.load_weights(*learner.weights())
            stats = collector.snapshot().behaviors.get(behavior)
            if stats is not None and stats.episodes >= min_episodes:  # recent episodes
                best = max(best, stats.return_sum / stats.episodes)
                history.append((collector.metrics.agent_steps, stats.episodes, best))
                stats.return_sum, stats.episodes = 0.0, 0
    finally:
        collector.close()
    return best, history


def run_marked(marker: str) -> list[psutil.Process]:
    """Every process of a run started with ``UNITY_ROLLOUT_TEST_RUN=marker`` in its
    environment (Ray's node processes, workers and Unity players inherit it)."""
    found = []
    for process in psutil.process_iter():
        try:
            if process.environ().get("UNITY_ROLLOUT_TEST_RUN") == marker:
                found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, ProcessLookupError):
            continue
    return found


def start_train_cli(marker: str, *args: str) -> subprocess.Popen:
    """``unity-rollout train --no-progress ARGS`` in a session of its own, every process of
    it marked for ``run_marked``; its output as text on ``stdout``."""
    return subprocess.Popen(
        [sys.executable, "-m", "driver.cli", "train", "--no-progress", *args],
        env={**os.environ, "UNITY_ROLLOUT_TEST_RUN": marker},
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def kill_run(driver: subprocess.Popen) -> None:
    """A test's last word on a run it started (a ``finally``): its session, SIGKILLed."""
    if driver.poll() is None:
        os.killpg(driver.pid, signal.SIGKILL)
        driver.wait()


def assert_run_gone(marker: str, seconds: float = 60) -> None:
    """Every process of the run exits within ``seconds``; leftovers are killed by PID and
    fail the test."""
    poll_until(lambda: not run_marked(marker), seconds)
    left = run_marked(marker)
    for process in left:
        with contextlib.suppress(psutil.NoSuchProcess):
            process.kill()
    assert not left, f"processes outlived the run: {[p.cmdline()[:3] for p in left]}"


def assert_rewards_per_episode(scalars: list[str], *signals: str) -> None:
    """As ML-Agents: a signal's ``Policy/<Signal> Reward`` is its sum per finished episode,
    so a short run whose rows were all cut at the horizon writes none."""
    ended = "Environment/Cumulative Reward" in scalars
    for name in signals:
        assert f"Policy/{name} Reward" not in scalars or ended, (name, scalars)
