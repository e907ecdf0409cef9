"""Workers without Unity for the benchmarks of the central parts: ``SyntheticWorker``
replays a few recorded collects as fast as the driver and the learner take them.
Tests and benchmarks only; not part of the installed product.
"""

from __future__ import annotations

import dataclasses
import os
import time
import uuid

import numpy as np

from batches import keys
from batches.contracts import ActorFactory, Weights
from batches.segment import Segment
from rollout.collecting.collector import Collector, CollectorMetrics
from rollout.collecting.horizons import Horizons
from rollout.collecting.ledger import Collected, Counts
from rollout.environment.ports import PortAllocator, PortRange
from rollout.environment.unity import UnityConfig


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

    Same constructor and calls as ``rollout.collecting.worker.RolloutWorker`` (``RolloutService``'s
    ``worker_class``); as a Ray actor: ``ray.remote(SyntheticWorker)``."""

    RECORDED = 4  # collects recorded at start, replayed in turn

    def __init__(
        self,
        index: int,
        unity: UnityConfig,
        actor_factory: ActorFactory,
        horizon: int | Horizons,
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
        parameters: object = None,  # no build to send them to
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
