"""What PPO and IMPALA share: the buffer of segments waiting for the next update, and one
gradient step on a loss's entries.

The buffer keeps whole packed segments (advantage estimators run along each trajectory,
which ``done`` ends) and counts the steps that will train; ``take`` hands them over as one
``[N]`` batch, observations folded into the running normalization, rewards scaled by the
extrinsic signal's strength, actions joined into the flat action the torchrl actor scores.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase

from batches import keys
from learners.counters import on_policy_wanted
from learners.devices import Compute
from learners.modules import add_flat_action
from learners.policies import ActorCritic

TRAIN = "train"  # bool per step: counts in the loss (False: context for the estimator only)


class SegmentBuffer:
    def __init__(self, buffer_size: int, compute: Compute | None = None) -> None:
        self.buffer_size = buffer_size
        self.compute = compute or Compute()
        self.segments: list[TensorDict] = []
        self.steps = 0

    def add(self, segment: TensorDict, keep: torch.Tensor | None = None) -> int:
        """Buffer a segment; ``keep`` (per step) narrows which steps train."""
        segment = segment.exclude(*keys.METADATA)
        if keep is None:
            keep = torch.ones_like(segment[keys.POLICY_VERSION], dtype=torch.bool)
        segment[TRAIN] = keep
        steps = int(keep.sum())
        if steps:
            self.segments.append(segment)
            self.steps += steps
        return steps

    def ready(self) -> bool:
        """More than ``buffer_size`` steps, as ML-Agents' trainers wait for."""
        return self.steps > self.buffer_size

    def wanted(self) -> int:
        return on_policy_wanted(self.buffer_size, self.steps)

    def take(self, network: ActorCritic, reward_strength: float) -> TensorDict:
        batch = self.compute.to_device(torch.cat(self.segments, dim=0))
        self.segments, self.steps = [], 0
        train, obs = batch[TRAIN], batch[keys.OBS]
        network.update_normalization({n: obs[n][train] for n in obs.keys()})  # noqa: SIM118
        batch[keys.NEXT, keys.REWARD] = batch[keys.NEXT, keys.REWARD] * reward_strength
        return add_flat_action(batch)


def set_learning_rate(optimizer: torch.optim.Optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr


def gradient_step(
    losses: TensorDictBase | Mapping[str, torch.Tensor],
    optimizer: torch.optim.Optimizer,
    totals: dict[str, float],
    max_grad_norm: float | None = None,
) -> None:
    """Sum a loss's ``loss_*`` entries, step, and add every entry's value to ``totals``."""
    loss = sum(v for k, v in losses.items() if k.startswith("loss_"))
    optimizer.zero_grad()
    loss.backward()
    if max_grad_norm is not None:
        params = [p for group in optimizer.param_groups for p in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm)
    optimizer.step()
    for key, value in losses.items():
        totals[key] = totals.get(key, 0.0) + float(value.detach().mean())
    totals["updates"] = totals.get("updates", 0.0) + 1


def means(totals: dict[str, float]) -> dict[str, float]:
    """Per gradient step: the mean of each loss entry ``gradient_step`` added up."""
    return {key: value / max(totals.get("updates", 0), 1) for key, value in totals.items()}


def actor_critic_report(mean: dict[str, float], lr: float, beta: float) -> dict[str, float]:
    """ML-Agents' names for an actor-critic loss's means over one update."""
    return {
        "Losses/Policy Loss": mean.get("loss_objective", 0.0),
        "Losses/Value Loss": mean.get("loss_critic", 0.0) * 2,  # undo critic_coeff 0.5
        "Policy/Entropy": mean.get("entropy", 0.0),
        "Policy/Learning Rate": lr,
        "Policy/Beta": beta,
    }
