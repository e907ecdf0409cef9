"""A minimal learner stand-in for tests and benchmarks of the rollout side.

It consumes segments, counts what it got (steps, trajectories, bytes, the policy versions
that acted), and publishes a new weights version every ``bump_every`` submissions, or, with
a ``demand``, once that many steps came since the last version (as an on-policy learner
would, "updating" for ``update_seconds``); handing out a new version takes ``weights_seconds``.
The weights themselves are empty: workers keep their own and stamp the newer version, so
tests and benchmarks can see versions reach the workers and measure policy lag.
"""

from __future__ import annotations

import dataclasses
import os
import time
import uuid
from collections import Counter

import numpy as np

from batches import keys
from batches.segment import Segment
from rollout.collector import ActorFactory, Collector, CollectorMetrics, Weights
from rollout.ledger import Collected, Counts
from rollout.ports import PortAllocator, PortRange
from rollout.unity import UnityConfig


class CountingLearner:
    def __init__(
        self,
        bump_every: int = 2,
        demand: int | None = None,
        update_seconds: float = 0.0,
        weights_seconds: float = 0.0,
    ) -> None:
        self.bump_every = bump_every
        self.demand, self.update_seconds = demand, update_seconds
        self.weights_seconds = weights_seconds  # publishing takes this long
        self.since_bump = 0  # steps since the last version (with a demand)
        self.version = 0
        self.submissions = 0
        self.steps: Counter[str] = Counter()
        self.trajectories: Counter[str] = Counter()
        self.bytes = 0
        self.versions_seen: Counter[int] = Counter()

    def submit(self, segments: list[Segment]) -> tuple[int, int | None]:
        for segment in segments:
            self.steps[segment.behavior] += len(segment)
            self.trajectories[segment.behavior] += int(segment.data[keys.NEXT][keys.DONE].sum())
            self.bytes += segment.nbytes
            self.versions_seen.update(segment.data[keys.POLICY_VERSION].tolist())
            self.since_bump += len(segment)
        if not segments:
            return self.version, self._wanted()
        self.submissions += 1
        if self.demand is None and self.submissions % self.bump_every == 0:
            self.version += 1
        if self.demand is not None and self.since_bump >= self.demand:
            time.sleep(self.update_seconds)
            self.version, self.since_bump = self.version + 1, 0
        return self.version, self._wanted()

    def _wanted(self) -> int | None:
        return None if self.demand is None else self.demand - self.since_bump

    def weights(self) -> tuple[int, Weights]:
        if self.version > 0:  # a new version (the first weights go out at the start)
            time.sleep(self.weights_seconds)
        return self.version, {}

    def summary(self) -> dict:
        return {
            "version": self.version,
            "submissions": self.submissions,
            "steps": dict(self.steps),
            "trajectories": dict(self.trajectories),
            "bytes": self.bytes,
            "versions_seen": dict(self.versions_seen),
        }


def replayed(segment: Segment, version: int, source: tuple[str, int]) -> Segment:
    """A recorded segment sent anew: acted by ``version``, from ``source`` (the learner
    takes each source once, and PPO drops steps of weights too old)."""
    versions = np.full(len(segment), version, dtype=np.int64)
    data = {**segment.data, keys.POLICY_VERSION: versions}
    return dataclasses.replace(segment, data=data, source=source)


class SyntheticWorker:
    """A rollout worker without Unity, for the ceilings of the central parts: it records a
    few real collects at start (one Unity instance, then closed) and answers every collect
    at once with one of them, under a new source number and the version it was sent, so
    the driver and the learner see a stream as fast as they can take it.

    Same constructor and calls as ``rollout.worker.RolloutWorker`` (``RolloutService``'s
    ``worker_class``); as a Ray actor: ``ray.remote(SyntheticWorker)``."""

    RECORDED = 4  # collects recorded at start, replayed in turn

    def __init__(
        self,
        index: int,
        unity: UnityConfig,
        actor_factory: ActorFactory,
        horizon: int,
        port_range: PortRange | None = None,
        registry_dir: str | None = None,
    ) -> None:
        collector = Collector(
            unity, actor_factory, horizon, index, PortAllocator(port_range, registry_dir)
        )
        try:
            self.recorded = [collector.collect(512) for _ in range(self.RECORDED)]
        finally:
            collector.close()
        self.metrics_ = CollectorMetrics(incarnation=uuid.uuid4().hex)
        self.counts: dict[str, Counts] = {}
        self.collects = 0

    def collect(
        self,
        version: int,
        published: tuple[int, Weights] | None,
        min_steps: int,
        max_seconds: float | None = None,
    ) -> Collected:
        started = time.perf_counter()
        if published is not None:
            self.metrics_.policy_version = published[0]
        template = self.recorded[self.collects % len(self.recorded)]
        self.collects += 1
        segments = []
        source = (self.metrics_.incarnation, self.collects)
        for segment in template:
            segments.append(replayed(segment, self.metrics_.policy_version, source))
            steps = len(segment)
            old = self.counts.get(segment.behavior, Counts())
            self.counts[segment.behavior] = Counts(old.produced + steps, old.emitted + steps)
            self.metrics_.agent_steps += steps
        self.metrics_.env_steps += 1
        self.metrics_.seconds += time.perf_counter() - started
        return Collected(segments, self.metrics_.incarnation, dict(self.counts))

    def metrics(self) -> CollectorMetrics:
        return self.metrics_

    def identity(self) -> dict[str, int | None]:
        return {"pid": os.getpid(), "player_pid": None, "port": None, "restarts": 0}

    def close(self) -> Collected:
        return Collected([], self.metrics_.incarnation, dict(self.counts))
