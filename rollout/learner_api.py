"""The contract between rollout workers and a learner (``learners`` implements it).

The service forwards each worker's segments (an ObjectRef to ``list[Segment]``, the
format of docs/batch-format.md; a ``rollout.ledger.Collected``, a list that also carries
the worker's counts for the sample ledger) with ``submit``; it keeps at most a few submissions in
flight, so a slow learner slows collection instead of growing a queue. ``submit`` returns
the learner's newest weights version, and its demand: how many more steps it wants before
its next on-policy update (None: any amount, as off-policy learners take). When the
version is newer than what workers have, the service fetches ``weights()`` once (one
object per version) and passes it to every worker's next ``collect``; while the steps in
flight cover the demand, it lets idle workers wait for those weights.
"""

from __future__ import annotations

from typing import Protocol

from batches.segment import Segment
from rollout.collector import Weights


class Learner(Protocol):
    def submit(self, segments: list[Segment]) -> tuple[int, int | None]:
        """Consume segments; return the newest weights version and the demand."""
        ...

    def weights(self) -> tuple[int, Weights]:
        """The newest version and its weights, behavior -> state_dict."""
        ...
