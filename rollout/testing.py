"""A minimal learner stand-in for tests and benchmarks of the rollout side.

It consumes segments (checking them against the behavior's spec), counts what it got,
and publishes a new weights version every ``bump_every`` submissions: the weights are
the initial ones shifted by the version, so tests can see them reach the workers.
"""

from __future__ import annotations

from collections import Counter

import torch
from tensordict import TensorDict

from rollout import keys
from rollout.collector import ActorFactory, Weights


class CountingLearner:
    def __init__(self, actor_factory: ActorFactory, bump_every: int = 2) -> None:
        self.actor_factory = actor_factory
        self.bump_every = bump_every
        self.version = 0
        self.submissions = 0
        self.valid_steps: Counter[str] = Counter()
        self.rows: Counter[str] = Counter()
        self.bytes = 0
        self._initial: Weights = {}
        self.versions_seen: Counter[int] = Counter()

    def submit(self, segments: list[TensorDict]) -> int:
        for segment in segments:
            behavior = segment.get_non_tensor(keys.BEHAVIOR)
            self.valid_steps[behavior] += int(segment[keys.VALID].sum())
            self.rows[behavior] += segment.batch_size[0]
            self.bytes += int(segment.bytes())
            self.versions_seen.update(segment[keys.POLICY_VERSION][segment[keys.VALID]].tolist())
        self.submissions += 1
        if self.submissions % self.bump_every == 0:
            self.version += 1
        return self.version

    def register(self, behavior: str, state: dict[str, torch.Tensor]) -> None:
        self._initial[behavior] = state

    def weights(self) -> tuple[int, Weights]:
        shifted = {
            behavior: {name: value + self.version for name, value in state.items()}
            for behavior, state in self._initial.items()
        }
        return self.version, shifted

    def summary(self) -> dict:
        return {
            "version": self.version,
            "submissions": self.submissions,
            "valid_steps": dict(self.valid_steps),
            "rows": dict(self.rows),
            "bytes": self.bytes,
            "versions_seen": dict(self.versions_seen),
        }
