"""The learner the rollout service feeds when the user's own loop learns
(``batches.contracts.Learner``): it holds what workers send until the collector takes a
batch, and publishes the weights the collector gives it.

Its demand keeps the workers one batch ahead of the consumer at most: it asks for the
steps a batch still lacks, and 0 (no more now) once it holds a batch, as an on-policy
learner holds workers back while it updates; the collector asks the service to ask again
(``RolloutService.ask_learner``) when it takes a batch.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from batches.contracts import Weights, base_name
from batches.segment import Segment, Sources

ALL = "*"  # a state for every behavior


class BatchQueue:
    def __init__(self, frames_per_batch: int, behavior: str | None = None) -> None:
        self.frames_per_batch = frames_per_batch
        self.behavior = behavior  # keep this behavior's steps only (None: all)
        self.segments: list[Segment] = []
        self.steps = 0
        self.version = 0
        self.states: dict[str, Mapping[str, Any]] = {}  # behavior name or ALL -> state
        self.seen: list[str] = []  # behavior ids, in order met
        self._sources = Sources()

    def submit(self, segments: list[Segment]) -> tuple[int, int]:
        for segment in segments:
            if segment.source is not None and not self._sources.first(segment):
                continue  # a delivery Ray retried
            if segment.behavior not in self.seen:
                self.seen.append(segment.behavior)
                if self.states:  # weights were published without it: its actors need them
                    self.version += 1
            if self.behavior is not None and base_name(segment.behavior) != self.behavior:
                continue
            self.segments.append(segment)
            self.steps += len(segment)
        return self.version, self.wanted()

    def wanted(self) -> int:
        return max(self.frames_per_batch - self.steps, 0)

    def take(self) -> list[Segment] | None:
        """A batch's worth of segments (at least ``frames_per_batch`` steps), or None."""
        if self.steps < self.frames_per_batch:
            return None
        taken, self.segments, self.steps = self.segments, [], 0
        return taken

    def publish(self, states: Mapping[str, Mapping[str, Any]]) -> int:
        """New weights: by behavior name (without ``?team=``), or ``ALL``."""
        self.states = dict(states)
        self.version += 1
        return self.version

    def weights(self) -> tuple[int, Weights]:
        out: Weights = {}
        for behavior in self.seen:
            state = self.states.get(base_name(behavior), self.states.get(ALL))
            if state is not None:
                out[behavior] = dict(state)
        return self.version, out
