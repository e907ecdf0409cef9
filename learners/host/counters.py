"""What the learner counts, without torch: the driver reads these (``progress``), and the
learner's Ray host counts the segments that arrive while its process still loads torch.

``LearnerStats``: the learner's throughput counters. ``all_done``: whether the
run has its steps, ``steps_left`` how many it still needs. ``on_policy_wanted``: an
on-policy behavior's demand, steps still missing before its next update; ``demand``: the
learner's, bounded by what the run still needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Mapping

    from learners.trainer_config.settings import RunConfig


def all_done(steps: Mapping[str, int], config: RunConfig, max_steps: int | None) -> bool:
    """Whether every behavior seen has its steps: ``max_steps`` (the CLI's ``--max-steps``)
    or else its config's ``max_steps``; none seen, not done."""
    return steps_left(steps, config, max_steps) == 0


def budget(behavior: str, config: RunConfig, max_steps: int | None) -> int:
    """A behavior's steps: ``max_steps`` (the CLI's ``--max-steps``), else its config's."""
    return max_steps or config.for_behavior(behavior).max_steps


def steps_left(steps: Mapping[str, int], config: RunConfig, max_steps: int | None) -> int | None:
    """Steps until every behavior seen has its steps (0: the run has them; None: none seen),
    what a learner asks for at most, so the run stops near its ``max_steps``."""
    if not steps:
        return None
    return max(
        max(budget(behavior, config, max_steps) - count, 0) for behavior, count in steps.items()
    )


def demand(
    steps: Mapping[str, int],
    config: RunConfig,
    max_steps: int | None,
    wants: list[int],
    inference: bool = False,
) -> int | None:
    """A learner's demand (``batches/contracts.py``): the least of its on-policy behaviors'
    ``wants`` (None: none has one, or ``inference`` trains nothing), never more than the run
    still needs (0: it has them all)."""
    if (left := steps_left(steps, config, max_steps)) == 0:
        return 0
    if inference or not wants:
        return None
    return min(wants) if left is None else min(*wants, left)


def on_policy_wanted(buffer_size: int, steps: int) -> int:
    """Steps still missing before a buffer of ``steps`` is ready (at least 1): ML-Agents'
    trainers update once more than ``buffer_size`` steps are in."""
    return max(buffer_size + 1 - steps, 1)


@dataclass
class LearnerStats:
    samples: int = 0  # valid steps consumed by updates
    update_seconds: float = 0.0
    submit_seconds: float = 0.0
    updates: int = 0
    duplicate_steps: int = 0  # segments delivered twice (Ray retries), taken once
