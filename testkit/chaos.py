"""A chaos driver: faults injected into a live run's processes on a schedule, for the chaos
benchmark (``benchmarks/costs/bench_chaos.py``) and its shorter test.

The run's processes are found under the ``unity-rollout train`` process it is given:
Ray's worker processes by their titles (``ray::RolloutWorker``, ``ray::RayLearner``) and
each Unity player as a child of a rollout worker, so the same driver works against a real
build. Faults, as they come in production:

- ``kill-player``: SIGKILL of a random Unity player (a crash);
- ``hang-player``: SIGSTOP of a random Unity player (alive, never answers: a hang);
- ``kill-worker``: SIGKILL of a random rollout worker (its node lost it);
- ``kill-learner``: SIGKILL of the learner (out of memory, a GPU error).
"""

from __future__ import annotations

import random
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import psutil

FAULTS = {
    "kill-player": ("player", signal.SIGKILL),
    "hang-player": ("player", signal.SIGSTOP),
    "kill-worker": ("worker", signal.SIGKILL),
    "kill-learner": ("learner", signal.SIGKILL),
}
TITLES = {"worker": "ray::RolloutWorker", "learner": "ray::RayLearner"}


@dataclass(frozen=True)
class Fault:
    """``kind`` every ``every_s`` seconds from ``first_s``, at most ``times`` times."""

    kind: str
    first_s: float
    every_s: float = 0.0
    times: int = 1

    def __post_init__(self) -> None:
        if self.kind not in FAULTS:
            raise ValueError(f"fault kind {self.kind!r}: one of {', '.join(FAULTS)}")

    def due(self) -> list[float]:
        return [self.first_s + i * self.every_s for i in range(self.times)]


@dataclass(frozen=True)
class Injected:
    at_s: float
    kind: str
    pid: int | None  # None: no such process was running then (counted, not injected)


def issue_schedule(duration_s: float, learner_at_s: float) -> list[Fault]:
    """The schedule of the chaos issue: a player crash every 30 s, a worker killed every
    2 min, a hang every 90 s, one learner kill."""

    def every(kind: str, period: float) -> Fault:
        return Fault(kind, period, period, max(int(duration_s // period), 0))

    return [
        every("kill-player", 30.0),
        every("kill-worker", 120.0),
        every("hang-player", 90.0),
        Fault("kill-learner", learner_at_s),
    ]


def processes(driver_pid: int, role: str) -> list[psutil.Process]:
    """The run's processes of one role: ``player``, ``worker`` or ``learner``."""
    try:
        tree = psutil.Process(driver_pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []

    def titled(process: psutil.Process, title: str) -> bool:
        try:
            return " ".join(process.cmdline()).startswith(title)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            return False

    if role in TITLES:
        return [p for p in tree if titled(p, TITLES[role])]
    players = []
    for worker in (p for p in tree if titled(p, TITLES["worker"])):
        try:
            players += [p for p in worker.children() if p.status() != psutil.STATUS_STOPPED]
        except psutil.NoSuchProcess:
            continue
    return players


class ChaosDriver:
    """Runs a schedule against a run on a thread; ``injected`` lists what it did."""

    def __init__(
        self,
        driver_pid: int,
        schedule: list[Fault],
        seed: int = 0,
        ready: Callable[[], bool] | None = None,
    ) -> None:
        """``ready``: when the schedule's clock starts (e.g. at the run's first summary: a
        run's first launch of a build is strict, a crash there ends it as a bad build)."""
        self.driver_pid = driver_pid
        self.ready = ready
        self.plan = sorted((at, f.kind) for f in schedule for at in f.due())
        self.random = random.Random(seed)
        self.injected: list[Injected] = []
        self.started = time.monotonic()  # the schedule's zero (set again once ready)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> ChaosDriver:
        self._thread.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        while self.ready is not None and not self.ready():  # the clock starts with training
            if self._stop.wait(0.2):
                return
        self.started = time.monotonic()
        for at, kind in self.plan:
            if self._stop.wait(max(0.0, self.started + at - time.monotonic())):
                return
            self.inject(kind)

    def inject(self, kind: str) -> Injected:
        role, signum = FAULTS[kind]
        candidates = processes(self.driver_pid, role)
        pid = None
        if candidates:
            target = self.random.choice(candidates)
            try:
                target.send_signal(signum)
                pid = target.pid
            except psutil.NoSuchProcess:
                pass
        done = Injected(round(time.monotonic() - self.started, 1), kind, pid)
        self.injected.append(done)
        return done

    def count(self, kind: str) -> int:
        """Faults of this kind that reached a process."""
        return sum(1 for i in self.injected if i.kind == kind and i.pid is not None)
