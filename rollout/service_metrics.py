"""What the rollout service counts, aggregated over its workers: steps, segments, policy
lag, faults (worker, Unity and learner restarts) and the steps they dropped."""

from __future__ import annotations

from dataclasses import dataclass, field

from rollout.collector import CollectorMetrics


@dataclass
class ServiceMetrics:
    env_steps: int = 0
    agent_steps: int = 0
    segments: int = 0
    worker_restarts: int = 0
    unity_restarts: int = 0
    dropped_steps: int = 0
    learner_restarts: int = 0
    learner_dropped_steps: int = 0  # in flight to, or acted by the weights of, a dead learner
    policy_lag_max: int = 0
    policy_lag_sum: int = 0
    policy_lag_count: int = 0
    seconds: float = 0.0
    workers: list[CollectorMetrics] = field(default_factory=list)

    def faults(self) -> dict[str, int]:
        """Every fault so far and the steps faults cost (live table, summary.json)."""
        return {
            "unity_restarts": self.unity_restarts,
            "worker_restarts": self.worker_restarts,
            "learner_restarts": self.learner_restarts,
            "dropped_steps": self.dropped_steps + self.learner_dropped_steps,
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

    def mean_returns(self) -> dict[str, float]:
        """Mean episode return per behavior, over every worker's finished episodes."""
        return {
            name: returns / episodes
            for name, (episodes, returns, _) in self.episode_totals().items()
            if episodes
        }
