"""PPO for one behavior, as mlagents-learn runs it, on torchrl's ``GAE``.

Reads top to bottom like one iteration of the algorithm, as mlagents-learn runs it:
segments arrive (``add``) and wait in a buffer until more than ``buffer_size`` steps are
there; ``update`` folds their observations into the running normalization, computes GAE
advantages along each packed trajectory (torchrl's estimator, which stops at ``done``
and bootstraps from the next observation unless ``terminated``), normalizes the
advantages over the whole buffer, and runs ``num_epoch`` passes of shuffled minibatches
of ``batch_size`` (the remainder left out) through ``loss``. Learning rate, epsilon
and beta decay linearly over ``max_steps`` to 1e-10, 0.1 and 1e-5, as ML-Agents'
do (``*_schedule: constant`` keeps them). No gradient clipping, as in ML-Agents.

The loss is ML-Agents', written out rather than torchrl's ``ClipPPOLoss``, because
``epsilon`` means something else there: ML-Agents clips the probability ratio of each
action component (each continuous dimension, each discrete branch) on its own and
averages the clipped surrogates; ``ClipPPOLoss`` clips the ratio of the joint action.
The value loss is the plain squared error, which is what mlagents-learn 1.1.0 computes
in effect: its code clips the value around the old estimate, but the old estimate it
reads is the return (``RewardSignalUtil.value_estimates_key`` names the returns' buffer
field), so the clip never binds. Clipping for real cost samples: 3DBall reached 90 at
a median 138k steps against 114k without (docs/benchmarks.md).

The buffer (``SegmentBuffer``, which IMPALA shares) keeps whole packed segments, since the
estimator runs along each trajectory, and hands them over as one ``[N]`` batch:
observations folded into the running normalization, rewards scaled by the extrinsic
signal's strength, actions joined into the flat action the torchrl actor scores.

Policy lag: workers act with slightly old weights. The surrogate's ratio is taken
against the log-probability stored with each step (the policy that really acted), which
corrects moderate lag; steps acted by weights more than ``max_policy_lag`` versions old
are dropped from the loss (they still serve as GAE context) and counted.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives.value import GAE

from batches import keys
from learners.counters import on_policy_wanted
from learners.devices import Compute
from learners.modules import add_flat_action, value_operator
from learners.policies import ActorCritic
from learners.schedules import BETA_END, EPSILON_END, decay

if TYPE_CHECKING:
    from learners.settings import TrainerSettings


# ---- the buffer of segments waiting for the next update (IMPALA's too) ---------------------

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


# ---- PPO ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Steps:
    """The steps of one update as plain tensors, ``[N, ...]`` each: a minibatch is then
    one gather per field (a TensorDict's per-key bookkeeping cost as much as the network)."""

    obs: dict[str, torch.Tensor]
    continuous: torch.Tensor | None
    discrete: torch.Tensor | None
    mask: torch.Tensor | None  # True = allowed
    log_prob: torch.Tensor  # [N, components], the acting policy's
    advantage: torch.Tensor  # [N]
    value_target: torch.Tensor  # [N]

    @classmethod
    def of(cls, steps: TensorDict) -> Steps:
        action = steps[keys.ACTION]
        return cls(
            obs=dict(steps[keys.OBS].items()),
            continuous=action.get(keys.CONTINUOUS, None),
            discrete=action.get(keys.DISCRETE, None),
            mask=steps.get(keys.ACTION_MASK, None),
            log_prob=steps[keys.LOG_PROB],
            advantage=steps["advantage"].squeeze(-1),
            value_target=steps["value_target"].squeeze(-1),
        )

    def __getitem__(self, index: torch.Tensor) -> Steps:
        def pick(tensor: torch.Tensor | None) -> torch.Tensor | None:
            return None if tensor is None else tensor[index]

        return Steps(
            {name: obs[index] for name, obs in self.obs.items()},
            pick(self.continuous),
            pick(self.discrete),
            pick(self.mask),
            self.log_prob[index],
            self.advantage[index],
            self.value_target[index],
        )


class PPO:
    def __init__(
        self, network: ActorCritic, settings: TrainerSettings, compute: Compute | None = None
    ) -> None:
        self.network, self.settings = network, settings
        self.compute = compute or Compute()
        h = settings.hyperparameters
        self.advantage = GAE(
            gamma=settings.gamma,
            lmbda=h.lambd,
            value_network=value_operator(network),
            average_gae=False,
        )
        self.optimizer = torch.optim.Adam(network.parameters(), lr=h.learning_rate, fused=True)
        self.buffer = SegmentBuffer(h.buffer_size, self.compute)
        self.stale_steps = 0

    # --- data in ------------------------------------------------------------------------

    def add(self, segment: TensorDict, lag: torch.Tensor) -> int:
        """Buffer a packed segment (``lag``: per step, updates of this behavior since the
        weights that acted); returns the steps that will count in the loss."""
        fresh = lag <= self.settings.hyperparameters.max_policy_lag
        self.stale_steps += int((~fresh).sum())
        return self.buffer.add(segment, keep=fresh)

    def ready(self) -> bool:
        return self.buffer.ready()

    def wanted(self) -> int | None:
        return self.buffer.wanted()

    # --- the update ---------------------------------------------------------------------

    def update(self, progress: float) -> dict[str, float]:
        """One PPO iteration on everything buffered; ``progress`` in [0, 1] drives schedules."""
        h = self.settings.hyperparameters
        batch = self.buffer.take(self.network, self.settings.reward_strength)
        with torch.no_grad():
            self.advantage(batch)
        steps = batch[batch[TRAIN]]  # the steps that train, each with advantage and target
        advantage = steps["advantage"]
        steps["advantage"] = (advantage - advantage.mean()) / (advantage.std() + 1e-10)

        schedule = h.learning_rate_schedule
        lr = decay(h.learning_rate, progress, schedule)
        epsilon = decay(h.epsilon, progress, h.epsilon_schedule or schedule, EPSILON_END)
        beta = decay(h.beta, progress, h.beta_schedule or schedule, BETA_END)
        set_learning_rate(self.optimizer, lr)
        totals: dict[str, float] = {}
        data = Steps.of(steps)
        for _ in range(h.num_epoch):
            order = torch.randperm(len(data.log_prob), device=data.log_prob.device)
            for index in order.split(h.batch_size):
                if len(index) == h.batch_size:
                    losses = self.loss(data[index], epsilon, beta)
                    gradient_step(losses, self.optimizer, totals)
        mean = means(totals)
        return {
            **actor_critic_report(mean, lr, beta),
            "Policy/Epsilon": epsilon,
            "Policy/Clip Fraction": mean.get("clip_fraction", 0.0),
            "Policy/Approx KL": mean.get("kl_approx", 0.0),
            "Policy/Extrinsic Value Estimate": float(steps["state_value"].mean()),
            "Policy/Stale Steps Dropped": float(self.stale_steps),
            "Policy/Samples": float(len(steps)),
        }

    def loss(self, steps: Steps, epsilon: float, beta: float) -> dict[str, torch.Tensor]:
        """ML-Agents' PPO loss on a minibatch: per-component clipped surrogate, squared
        value error (weight 0.5), entropy bonus (weight ``beta``)."""
        log_prob, entropy, value = self.network.evaluate(
            steps.obs, steps.continuous, steps.discrete, steps.mask
        )
        log_ratio = log_prob - steps.log_prob
        ratio = log_ratio.exp()  # [B, components]
        advantage = steps.advantage.unsqueeze(-1)
        surrogate = torch.min(ratio * advantage, ratio.clamp(1 - epsilon, 1 + epsilon) * advantage)
        value_loss = (steps.value_target - value).square()
        entropy = entropy.mean()
        return {
            "loss_objective": -surrogate.mean(),
            "loss_critic": 0.5 * value_loss.mean(),
            "loss_entropy": -beta * entropy,
            "entropy": entropy.detach(),
            "clip_fraction": ((ratio - 1.0).abs() > epsilon).float().mean(),
            "kl_approx": -log_ratio.detach().mean(),
        }

    # --- checkpoints --------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {"optimizer": self.optimizer.state_dict(), "stale_steps": self.stale_steps}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
        self.stale_steps = int(state.get("stale_steps", 0))
