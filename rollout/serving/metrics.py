"""What the rollout service counts, aggregated over its workers: steps, segments, policy
lag, faults (worker, Unity and learner restarts) and the steps they dropped; and how it
gathers the workers' reports."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Any

import ray
from mlagents_envs.side_channel.stats_side_channel import StatsAggregationMethod
from ray.exceptions import RayActorError

from batches import keys
from rollout.collecting.collector import CollectorMetrics
from rollout.collecting.ledger import SHUTDOWN

HISTOGRAM_KEEP = 10_000  # values of one histogram statistic kept per summary period


@dataclass
class Stat:
    """One of Unity's custom statistics (``StatsRecorder``) over a summary period,
    aggregated as mlagents-learn does: SUM summed, MOST_RECENT the newest (worker 0's
    only), AVERAGE and HISTOGRAM averaged, HISTOGRAM's values kept for its histogram.
    Constant in size whatever the period's length."""

    method: StatsAggregationMethod
    count: int = 0
    total: float = 0.0
    last: float = 0.0
    values: list[float] = field(default_factory=list)

    def add(self, value: float) -> None:
        self.count += 1
        self.total += value
        self.last = value
        if self.method == StatsAggregationMethod.HISTOGRAM and len(self.values) < HISTOGRAM_KEEP:
            self.values.append(value)

    def merge(self, other: Stat) -> None:
        self.count += other.count
        self.total += other.total
        self.last = other.last
        self.values.extend(other.values[: HISTOGRAM_KEEP - len(self.values)])

    @property
    def value(self) -> float:
        if self.method == StatsAggregationMethod.SUM:
            return self.total
        if self.method == StatsAggregationMethod.MOST_RECENT:
            return self.last
        return self.total / max(self.count, 1)


def merge_stats(into: dict[str, Stat], new: dict[str, Stat]) -> None:
    for key, stat in new.items():
        if key in into:
            into[key].merge(stat)
        else:
            into[key] = Stat(stat.method)
            into[key].merge(stat)


@dataclass
class ServiceMetrics:
    env_steps: int = 0
    agent_steps: int = 0
    segments: int = 0
    worker_restarts: int = 0
    unity_restarts: int = 0
    dropped_steps: int = 0
    learner_restarts: int = 0
    dropped_by_reason: dict[str, int] = field(default_factory=dict)  # the sample ledger's
    policy_lag_max: int = 0
    policy_lag_sum: int = 0
    policy_lag_count: int = 0
    seconds: float = 0.0
    workers: list[CollectorMetrics] = field(default_factory=list)
    unity_stats: dict[str, Stat] = field(default_factory=dict)  # since the last drain
    specs: dict[str, dict[str, Any]] = field(default_factory=dict)  # behaviors seen so far

    def drain_unity_stats(self) -> dict[str, Stat]:
        """Unity's custom statistics since the last call (the summaries take them)."""
        stats, self.unity_stats = self.unity_stats, {}
        return stats

    def take(self, workers: list[CollectorMetrics]) -> None:
        """Totals over the workers' reports (restarted workers' included)."""
        self.workers = workers
        self.env_steps = sum(w.env_steps for w in workers)
        self.agent_steps = sum(w.agent_steps for w in workers)
        self.unity_restarts = sum(w.restarts for w in workers)
        self.dropped_steps = sum(w.dropped_steps for w in workers)
        for worker in workers:  # behaviors seen, before their first rows arrive
            for behavior, spec in worker.specs.items():
                self.specs.setdefault(behavior, spec)

    def observe(self, version: int, segments: list) -> None:
        """Segments routed while ``version`` is the newest: their count and policy lag."""
        for segment in segments:
            self.segments += 1
            self.specs.setdefault(segment.behavior, segment.spec)
            lag = version - segment.data[keys.POLICY_VERSION]
            if lag.size:
                self.policy_lag_max = max(self.policy_lag_max, int(lag.max()))
                self.policy_lag_sum += int(lag.sum())
                self.policy_lag_count += int(lag.size)

    def faults(self) -> dict[str, int]:
        """Every fault so far and the steps faults cost (live table, summary.json)."""
        return {
            "unity_restarts": self.unity_restarts,
            "worker_restarts": self.worker_restarts,
            "learner_restarts": self.learner_restarts,
            # the ledger's drops but those of the run's own end
            "dropped_steps": sum(n for r, n in self.dropped_by_reason.items() if r != SHUTDOWN),
        }

    @property
    def policy_lag_mean(self) -> float:
        return self.policy_lag_sum / max(self.policy_lag_count, 1)

    def episode_totals(self) -> dict[str, tuple[int, float, int]]:
        """Per behavior, over live workers: (episodes, return sum, length sum) so far."""
        totals: dict[str, tuple[int, float, int]] = {}
        for worker in self.workers:
            for name, stats in worker.behaviors.items():
                episodes, returns, lengths = totals.get(name, (0, 0.0, 0))
                totals[name] = (
                    episodes + stats.episodes,
                    returns + stats.return_sum,
                    lengths + stats.length_sum,
                )
        return totals

    def episode_extras(self) -> dict[str, tuple[float, float]]:
        """Per behavior, over live workers: the group rewards and the groupmates' rewards
        within the episodes of ``episode_totals`` so far."""
        extras: dict[str, tuple[float, float]] = {}
        for worker in self.workers:
            for name, stats in worker.behaviors.items():
                group, mates = extras.get(name, (0.0, 0.0))
                extras[name] = (group + stats.episode_group_sum, mates + stats.episode_mates_sum)
        return extras

    def group_totals(self) -> dict[str, tuple[int, float]]:
        """Per behavior with groups, over live workers: (episodes that ended with their
        group, their group rewards' sum) so far."""
        totals: dict[str, tuple[int, float]] = {}
        for worker in self.workers:
            for name, stats in worker.behaviors.items():
                if stats.group_episodes:
                    episodes, rewards = totals.get(name, (0, 0.0))
                    totals[name] = (
                        episodes + stats.group_episodes,
                        rewards + stats.group_return_sum,
                    )
        return totals

    def mean_returns(self) -> dict[str, float]:
        """Mean episode return per behavior, over every worker's finished episodes."""
        return {
            name: returns / episodes
            for name, (episodes, returns, _) in self.episode_totals().items()
            if episodes
        }


class WorkerReports:
    """The workers' newest metrics, never waiting on a worker: a hung player holds its
    worker in ``step`` until ``timeout_wait``, so one ``metrics`` call per worker is in
    flight, answered between its collects, and a busy worker counts with what it last
    reported. A restarted worker (a new incarnation) adds to what its last one did."""

    def __init__(self) -> None:
        self.calls: dict[int, ray.ObjectRef] = {}  # worker index -> its metrics call
        self._reported: dict[int, CollectorMetrics] = {}  # worker index -> its last report
        self._retired: list[CollectorMetrics] = []  # last reports of restarted workers
        self.unity_stats: dict[str, Stat] = {}  # reported since the service last took them

    def poll(self, workers: list[Any], wait_s: float) -> list[CollectorMetrics]:
        for index, worker in enumerate(workers):
            if worker is not None and index not in self.calls:
                self.calls[index] = worker.metrics.remote()
        calls = list(self.calls.values())
        answered, _ = ray.wait(calls, num_returns=len(calls), timeout=wait_s)
        for index, call in list(self.calls.items()):
            if call in answered:
                del self.calls[index]
                with contextlib.suppress(RayActorError):  # died: its last report stands
                    report = ray.get(call)
                    last = self._reported.get(index)
                    if last is not None and last.incarnation != report.incarnation:
                        self._retired.append(last)
                    self._reported[index] = report
                    self._take_stats(index, report.unity_stats)
        return self._retired + [self._reported[i] for i in sorted(self._reported)]

    def _take_stats(self, index: int, reported: dict[str, list[tuple[float, int]]]) -> None:
        """A report's statistics (each report carries those since its worker's last one);
        MOST_RECENT from worker 0 alone, as mlagents-learn takes it from its first env."""
        for key, values in reported.items():
            for value, code in values:
                method = StatsAggregationMethod(code)
                if method == StatsAggregationMethod.MOST_RECENT and index != 0:
                    continue
                self.unity_stats.setdefault(key, Stat(method)).add(value)

    def drain_stats(self) -> dict[str, Stat]:
        stats, self.unity_stats = self.unity_stats, {}
        return stats
