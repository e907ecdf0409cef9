"""The learner of ``unity-rollout collect``, a pipeline check without training, and the
stand-in learner of the rollout side's tests and benchmarks.

It consumes segments, counts what it got (steps, trajectories, bytes, the policy versions
that acted), and publishes a new weights version every ``bump_every`` submissions, or, with
a ``demand``, once that many steps came since the last version (as an on-policy learner
would, "updating" for ``update_seconds``, or with ``hold_updates`` until ``release``: a test sees
what happens during an update without timing it); handing out a new version takes
``weights_seconds``.
The weights themselves are empty: workers keep their own and stamp the newer version, so
tests and benchmarks can see versions reach the workers and measure policy lag.
"""

from __future__ import annotations

import threading
import time
from collections import Counter

from batches import keys
from batches.contracts import Weights
from batches.segment import Segment

HOLD_S = 120.0  # a held update ends by itself after this long (a safety stop)


class CountingLearner:
    def __init__(
        self,
        bump_every: int = 2,
        demand: int | None = None,
        update_seconds: float = 0.0,
        weights_seconds: float = 0.0,
        hold_updates: bool = False,
    ) -> None:
        """``hold_updates``: each update waits for ``release``, up to ``HOLD_S``. Give
        ``summary`` and ``release`` a Ray concurrency group of their own, as the real
        learner's status calls have: with a thread for every call instead, a second
        submission during the hold would hold a thread too."""
        self.bump_every = bump_every
        self.hold_updates = hold_updates
        self.released = threading.Event()
        self.updating = False
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
            self.updating = True
            time.sleep(self.update_seconds)
            if self.hold_updates:
                self.released.wait(HOLD_S)
                self.released.clear()
            self.version, self.since_bump = self.version + 1, 0
            self.updating = False
        return self.version, self._wanted()

    def _wanted(self) -> int | None:
        return None if self.demand is None else self.demand - self.since_bump

    def weights(self) -> tuple[int, Weights]:
        if self.version > 0:  # a new version (the first weights go out at the start)
            time.sleep(self.weights_seconds)
        return self.version, {}

    def release(self) -> None:
        """Let a held update end."""
        self.released.set()

    def summary(self) -> dict:
        return {
            "version": self.version,
            "updating": self.updating,
            "submissions": self.submissions,
            "steps": dict(self.steps),
            "trajectories": dict(self.trajectories),
            "bytes": self.bytes,
            "versions_seen": dict(self.versions_seen),
        }
