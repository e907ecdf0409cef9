"""IMPALA for one behavior: V-trace targets (torchrl's ``vtrace_advantage_estimate``) and
an actor-critic loss (torchrl's ``A2CLoss``), for fully asynchronous collection.

Unlike PPO, no step is dropped for being old: V-trace corrects each step against the
log-probability of the policy that really acted, with truncated importance weights
(``vtrace_rho_clip``, ``vtrace_c_clip``). One update per ``buffer_size`` steps: each epoch
computes V-trace targets along every trajectory under the newest weights, then takes
shuffled minibatches of steps, each its own gradient step.

torchrl's ``VTrace`` module re-samples an action to get the current log-probability; the
importance ratio needs the log-probability of the action taken, so this file evaluates
the policy on the stored action itself and calls the same functional estimator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import A2CLoss
from torchrl.objectives.value.functional import vtrace_advantage_estimate

from batches import keys
from learners.algorithms.minibatch import set_learning_rate
from learners.algorithms.ppo import actor_critic_report
from learners.algorithms.schedules import decay
from learners.host.devices import Compute
from learners.networks.policies import ActorCritic
from learners.networks.torchrl_views import (
    FLAT_ACTION,
    add_flat_action,
    obs_keys,
    probabilistic_actor,
    value_operator,
)
from learners.reward_signals.extrinsic import extrinsic_reward

if TYPE_CHECKING:
    from learners.trainer_config.settings import TrainerSettings


def gradient_step(
    losses: TensorDictBase, optimizer: torch.optim.Optimizer, totals: dict[str, Any]
) -> None:
    """Sum a loss's ``loss_*`` entries, step with the gradient clipped to norm 0.5, and add
    every entry's value to ``totals`` (as tensors: read once per update), and the step's
    |objective| (``objective_size``: what ``actor_critic_report`` reports, as for PPO)."""
    loss = sum(v for k, v in losses.items() if k.startswith("loss_"))
    params = [p for group in optimizer.param_groups for p in group["params"]]
    for param in params:
        param.grad = None
    loss.backward()
    torch.nn.utils.clip_grad_norm_(params, 0.5)
    optimizer.step()
    with torch.no_grad():
        for key, value in losses.items():
            totals[key] = totals.get(key, 0.0) + value.detach().mean()
        size = losses["loss_objective"].detach().abs()
        totals["objective_size"] = totals.get("objective_size", 0.0) + size
    totals["updates"] = totals.get("updates", 0) + 1


def means(totals: dict[str, Any]) -> dict[str, float]:
    """Per gradient step: the mean of each loss entry ``gradient_step`` added up."""
    steps = max(int(totals.get("updates", 0)), 1)
    return {key: float(value) / steps for key, value in totals.items()}


class SegmentBuffer:
    """Whole packed segments until more than ``buffer_size`` steps are there: V-trace runs
    along each trajectory, and every epoch recomputes it under the newest weights."""

    def __init__(self, buffer_size: int, compute: Compute | None = None) -> None:
        self.buffer_size = buffer_size
        self.compute = compute or Compute()
        self.segments: list[TensorDict] = []
        self.steps = 0

    def add(self, segment: TensorDict) -> int:
        self.segments.append(segment.exclude(*keys.METADATA))
        self.steps += segment.batch_size[0]
        return segment.batch_size[0]

    def ready(self) -> bool:
        """More than ``buffer_size`` steps, as ML-Agents' trainers wait for."""
        return self.steps > self.buffer_size

    def take(self, network: ActorCritic, reward_strength: float) -> TensorDict:
        batch = self.compute.to_device(torch.cat(self.segments, dim=0))
        self.segments, self.steps = [], 0
        network.update_normalization(dict(batch[keys.OBS].items()))
        batch[keys.NEXT, keys.REWARD] = extrinsic_reward(batch) * reward_strength
        return add_flat_action(batch)


class IMPALA:
    def __init__(
        self, network: ActorCritic, settings: TrainerSettings, compute: Compute | None = None
    ) -> None:
        self.network, self.settings = network, settings
        self.compute = compute or Compute()
        h = settings.hyperparameters
        self.actor, self.critic = probabilistic_actor(network), value_operator(network)
        self.loss = A2CLoss(
            self.actor,
            self.critic,
            entropy_coeff=h.beta,
            critic_coeff=0.5,
            loss_critic_type="l2",
            functional=False,
        )
        self.loss.set_keys(action=FLAT_ACTION, sample_log_prob=keys.LOG_PROB)
        self.optimizer = torch.optim.Adam(network.parameters(), lr=h.learning_rate, fused=True)
        self.buffer = SegmentBuffer(h.buffer_size, self.compute)
        self.max_lag_seen = 0

    def add(self, segment: TensorDict, lag: torch.Tensor) -> int:
        """Buffer a packed segment; every step counts, however old."""
        if lag.numel():
            self.max_lag_seen = max(self.max_lag_seen, int(lag.max()))
        return self.buffer.add(segment)

    def ready(self) -> bool:
        return self.buffer.ready()

    def wanted(self) -> None:
        return None  # V-trace corrects old data: no need to wait for fresh weights

    def vtrace(self, rows: TensorDict) -> TensorDict:
        """Set ``advantage`` and ``value_target`` on packed trajectories (no gradient)."""
        h = self.settings.hyperparameters
        with torch.no_grad():
            log_pi = self.actor.get_dist(rows).log_prob(rows[FLAT_ACTION]).unsqueeze(-1)
            log_mu = rows[keys.LOG_PROB].sum(-1, keepdim=True)  # the acting policy's
            value = self.critic(rows.select(*obs_keys(self.network)))["state_value"]
            next_rows = rows[keys.NEXT].select(*obs_keys(self.network))
            next_value = self.critic(next_rows)["state_value"]
            advantage, target = vtrace_advantage_estimate(
                self.settings.gamma,
                log_pi,
                log_mu,
                value,
                next_value,
                rows[keys.NEXT, keys.REWARD],
                rows[keys.NEXT, keys.DONE],
                rows[keys.NEXT, keys.TERMINATED],
                rho_thresh=h.vtrace_rho_clip,
                c_thresh=h.vtrace_c_clip,
                time_dim=-2,
            )
        rows.set("advantage", advantage)
        rows.set("value_target", target)
        rows.set("rho", (log_pi - log_mu).exp())
        return rows

    def update(self, progress: float) -> dict[str, float]:
        h = self.settings.hyperparameters
        batch = self.buffer.take(self.network, self.settings.reward_strength)
        lr = decay(h.learning_rate, progress, h.learning_rate_schedule)
        set_learning_rate(self.optimizer, lr)
        totals: dict[str, Any] = {}
        samples, rho_sum, value_sum = 0, 0.0, 0.0
        for _ in range(h.num_epoch):
            batch = self.vtrace(batch)  # targets under the newest weights
            for index in torch.randperm(len(batch), device=batch.device).split(h.batch_size):
                if len(index) < 2:
                    continue
                steps = batch[index]
                gradient_step(self.loss(steps), self.optimizer, totals)
                samples += len(steps)
                rho_sum += float(steps["rho"].sum())
                value_sum += float(steps["value_target"].sum())
        return {
            **actor_critic_report(means(totals), lr, h.beta),
            "Policy/Extrinsic Value Estimate": value_sum / max(samples, 1),
            "Policy/Mean Importance Ratio": rho_sum / max(samples, 1),
            "Policy/Max Lag Seen": float(self.max_lag_seen),
            "Policy/Samples": float(samples // max(h.num_epoch, 1)),
        }

    def state_dict(self) -> dict[str, Any]:
        return {"optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
