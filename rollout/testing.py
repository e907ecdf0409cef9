"""A minimal learner stand-in for tests and benchmarks of the rollout side.

It consumes segments, counts what it got (steps, rows, bytes, the policy versions that
acted), and publishes a new weights version every ``bump_every`` submissions. The
weights themselves are empty: workers keep their own and stamp the newer version, so
tests and benchmarks can see versions reach the workers and measure policy lag.
"""

from __future__ import annotations

from collections import Counter

from tensordict import TensorDict

from rollout import keys
from rollout.collector import Weights


class CountingLearner:
    def __init__(self, bump_every: int = 2) -> None:
        self.bump_every = bump_every
        self.version = 0
        self.submissions = 0
        self.valid_steps: Counter[str] = Counter()
        self.rows: Counter[str] = Counter()
        self.bytes = 0
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

    def weights(self) -> tuple[int, Weights]:
        return self.version, {}

    def summary(self) -> dict:
        return {
            "version": self.version,
            "submissions": self.submissions,
            "valid_steps": dict(self.valid_steps),
            "rows": dict(self.rows),
            "bytes": self.bytes,
            "versions_seen": dict(self.versions_seen),
        }
