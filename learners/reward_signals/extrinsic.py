"""The extrinsic reward signal of a step, as mlagents-learn 1.1.0 computes it.

ML-Agents' ``ExtrinsicRewardProvider`` adds the group reward (``AddGroupReward``) to the
agent's own whenever its buffer holds group rewards, which every trajectory's does: so
PPO and SAC train on group rewards too, without POCA's critic. POCA adds, besides, the
groupmates' own rewards of the same step (``learners/algorithms/poca.py``). What each learner then
scales by ``reward_signals.extrinsic.strength``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from batches import keys

if TYPE_CHECKING:
    import torch
    from tensordict import TensorDictBase


def extrinsic_reward(segment: TensorDictBase) -> torch.Tensor:
    """``[N, 1]``: each step's reward plus its group's."""
    return segment[keys.NEXT, keys.REWARD] + segment[keys.NEXT, keys.GROUP_REWARD]
