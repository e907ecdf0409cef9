"""Elastic membership: the workers follow the cluster's size while a run is live.

With ``--workers auto`` the service holds one worker per ``worker_cpus`` the cluster has
left after the learner's share, and looks again every few seconds: when a node joins (or
an autoscaler adds one), new workers start and take the current weights with their first
collect; when a node leaves (drained, preempted, stopped), its workers die with it and are
retired: their rows in progress count as dropped (the ledger's ``worker death``) and the
run goes on with the rest. Retired workers are not restarted in place: the cluster decides,
by the room it has, how many come back and where.

With an autoscaler (KubeRay's, the cluster launcher's), ``request_workers`` asks it for
room for ``--max-workers`` workers: it adds nodes up to its group's maximum, and the
workers follow as those nodes join.

A worker that dies before it ever delivered is a failure, not a departure: after
``max_barren`` such deaths in a row (a build that cannot start anywhere) the run stops.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import ray


def cluster_slots(worker_cpus: float, learner_cpus: float) -> int:
    """Workers the cluster holds now: one per ``worker_cpus`` of its CPUs (alive nodes)
    after ``learner_cpus``; at least one."""
    cpus = float(ray.cluster_resources().get("CPU", 0.0))
    return max(1, math.floor((cpus - learner_cpus) / worker_cpus + 1e-9))


def workers_wanted(worker_cpus: float, learner_cpus: float, max_workers: int | None) -> int:
    """How many workers an elastic run holds now: the cluster's slots, at most
    ``max_workers``."""
    slots = cluster_slots(worker_cpus, learner_cpus)
    return min(slots, max_workers or slots)


@dataclass
class Membership:
    worker_cpus: float = 1.0
    learner_cpus: float = 1.0
    max_workers: int | None = None  # never more than this many live
    every_s: float = 2.0  # how often the cluster's size is read
    max_barren: int = 3
    retired: set[int] = field(default_factory=set)  # worker indices gone for good
    delivered: set[int] = field(default_factory=set)  # indices that delivered a collect
    started: int = 0  # workers at the start
    added: int = 0
    barren: int = 0  # deaths in a row of workers that never delivered
    _next_check: float = 0.0

    def missing(self, live: list[int]) -> int:
        """Workers to add now: the cluster's slots past the ``live`` ones. None while one
        of those is still joining (no collect yet): it may be waiting for room that the
        cluster's view, seconds behind a node's departure, still shows."""
        now = time.monotonic()
        if now < self._next_check or not self.delivered.issuperset(live):
            return 0
        self._next_check = now + self.every_s
        wanted = workers_wanted(self.worker_cpus, self.learner_cpus, self.max_workers)
        return max(0, wanted - len(live))

    def summary(self) -> dict[str, int]:
        """For summary.json: workers that joined after the start, that left, and live."""
        return {"added": self.added, "removed": self.removed, "live": self.live}

    @property
    def removed(self) -> int:
        return len(self.retired)

    @property
    def live(self) -> int:
        return self.started + self.added - self.removed

    def delivered_by(self, index: int) -> None:
        self.delivered.add(index)
        self.barren = 0

    def retire(self, index: int) -> bool:
        """A worker died; False once too many in a row died before delivering anything."""
        self.retired.add(index)
        if index not in self.delivered:
            self.barren += 1
        return self.barren <= self.max_barren


def request_workers(workers: int, worker_cpus: float, learner_cpus: float) -> None:
    """Ask the cluster's autoscaler for room for ``workers`` and the learner, now rather
    than when tasks queue (an elastic service never queues any). Without an autoscaler
    (local mode, a fixed cluster) nothing reads the request."""
    from ray.autoscaler.sdk import request_resources

    bundles = [{"CPU": worker_cpus}] * workers
    if learner_cpus:
        bundles.append({"CPU": learner_cpus})
    request_resources(bundles=bundles)
