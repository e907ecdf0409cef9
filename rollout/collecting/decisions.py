"""What a worker's policy chose for the decision agents of one exchange, and the action
masks it chose under: what ``rollout.collecting.segments.SegmentBuilder.act`` records."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mlagents_envs.base_env import DecisionSteps


@dataclass(frozen=True)
class Decisions:
    """What the policy chose for the decision agents of one exchange, in their order."""

    continuous: np.ndarray  # float32 (n, continuous size)
    discrete: np.ndarray  # int64 (n, branches)
    log_prob: np.ndarray  # float32 (n, continuous size + branches): one per component
    # float32 (n, memory size): what a recurrent policy left for the agents' next decisions
    # (what it read is the builder's own: SegmentBuilder.memories)
    after: np.ndarray | None = None


def allowed_mask(decisions: DecisionSteps, size: int) -> np.ndarray:
    """ML-Agents' per-branch masks (True = forbidden) as one flat allowed-mask."""
    if decisions.action_mask is None:
        return np.ones((len(decisions), size), np.bool_)
    return ~np.concatenate(decisions.action_mask, axis=1)
