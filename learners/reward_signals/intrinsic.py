"""Intrinsic reward signals beside the extrinsic one, as ML-Agents' reward providers
compute and train them: ``rnd`` (random network distillation) and ``curiosity`` (the
intrinsic curiosity module). PPO (``learners/algorithms/ppo.py``) gives each signal a value head of
its own on the critic and a GAE with its own gamma, sums the signals' advantages, and
trains each signal's networks once per minibatch of its update.

Each signal's networks follow its own ``network_settings``: the same encoders and MLP
body as a policy's (``learners/networks/policies.py``'s ``ActorCritic``, whose trunk is
ML-Agents' ``NetworkBody``; only its encoders and trunk are used), initialized as
ML-Agents initializes them. Neither signal stops at an episode's end (ML-Agents'
``ignore_done``): its value bootstraps from the terminal observation.

- ``rnd``: a fixed random body and a trained one; the reward of a step is the squared
  distance between their features (summed), the loss its mean.
- ``curiosity``: a body encodes a step's observation and the next; an inverse model
  predicts the action from both, a forward model the next encoding from the first and the
  action; the reward is half the forward model's squared error (summed), capped at
  ``1 / strength``, and 0 until the signal's first update. The loss is 10 x (0.2 x forward
  + 0.8 x inverse), as in ML-Agents.
"""

from __future__ import annotations

from typing import Any

import torch
from mlagents_envs.base_env import BehaviorSpec
from torch import nn

from learners.networks.initializers import kaiming, xavier
from learners.reward_signals.base import EPSILON, NetworkBody, Signal, Transitions, flat_actions
from learners.trainer_config.settings import RewardSignalSettings


class RND(Signal):
    stat = "Rnd"

    def __init__(self, spec: BehaviorSpec, settings: RewardSignalSettings) -> None:
        super().__init__(settings)
        self.target = NetworkBody(spec, settings.network_settings).requires_grad_(False)
        self.predictor = NetworkBody(spec, settings.network_settings)
        self.optimizer = torch.optim.Adam(
            self.predictor.trained(), settings.learning_rate, fused=True
        )

    def _error(self, steps: Transitions) -> torch.Tensor:
        with torch.no_grad():
            target = self.target(steps.obs)
        return (self.predictor(steps.obs) - target).square().sum(-1)

    def rewards(self, steps: Transitions) -> torch.Tensor:
        with torch.no_grad():
            return self._error(steps)

    def update(
        self, steps: Transitions, generator: torch.Generator | None = None
    ) -> dict[str, float]:
        loss = self._error(steps).mean()
        self._step(loss)
        return {"Losses/RND Loss": float(loss.detach())}

    def update_normalization(self, steps: Transitions) -> None:
        self.target.update_normalization(steps.obs)
        self.predictor.update_normalization(steps.obs)


class Curiosity(Signal):
    stat = "Curiosity"
    reads_next_obs = True
    FORWARD_WEIGHT, LOSS_MULTIPLIER, HIDDEN = 0.2, 10.0, 256

    def __init__(self, spec: BehaviorSpec, settings: RewardSignalSettings) -> None:
        super().__init__(settings)
        self.body = NetworkBody(spec, settings.network_settings)
        width, actions = self.body.width, spec.action_spec
        self.continuous = actions.continuous_size
        self.branches = tuple(actions.discrete_branches)
        flat = self.continuous + sum(self.branches)
        self.inverse = nn.Sequential(kaiming(2 * width, self.HIDDEN), nn.SiLU())
        self.continuous_head = xavier(self.HIDDEN, self.continuous) if self.continuous else None
        self.discrete_head = xavier(self.HIDDEN, sum(self.branches)) if self.branches else None
        self.forward_model = nn.Sequential(
            kaiming(width + flat, self.HIDDEN), nn.SiLU(), xavier(self.HIDDEN, width)
        )
        models = (self.inverse, self.continuous_head, self.discrete_head, self.forward_model)
        trained = [p for m in models if m is not None for p in m.parameters()]
        self.optimizer = torch.optim.Adam(
            [*self.body.trained(), *trained], settings.learning_rate, fused=True
        )
        self.updated = False

    def _forward_error(
        self, state: torch.Tensor, after: torch.Tensor, steps: Transitions
    ) -> torch.Tensor:
        predicted = self.forward_model(
            torch.cat([state, flat_actions(steps, self.continuous, self.branches)], dim=-1)
        )
        return 0.5 * (after - predicted).square().sum(-1)

    def rewards(self, steps: Transitions) -> torch.Tensor:
        if not self.updated:
            return torch.zeros(len(next(iter(steps.obs.values()))), device=self._device())
        with torch.no_grad():
            error = self._forward_error(self.body(steps.obs), self.body(steps.next_obs), steps)
        return error.clamp(max=1.0 / self.strength) if self.strength else error

    def update(
        self, steps: Transitions, generator: torch.Generator | None = None
    ) -> dict[str, float]:
        self.updated = True
        state, after = self.body(steps.obs), self.body(steps.next_obs)
        forward = self._forward_error(state, after, steps).mean()
        inverse = self._inverse_loss(torch.cat([state, after], dim=-1), steps)
        w = self.FORWARD_WEIGHT
        self._step(self.LOSS_MULTIPLIER * (w * forward + (1.0 - w) * inverse))
        return {
            "Losses/Curiosity Forward Loss": float(forward.detach()),
            "Losses/Curiosity Inverse Loss": float(inverse.detach()),
        }

    def _inverse_loss(self, both: torch.Tensor, steps: Transitions) -> torch.Tensor:
        hidden = self.inverse(both)
        loss = torch.zeros((), device=both.device)
        if self.continuous_head is not None:
            predicted = self.continuous_head(hidden)
            loss = loss + (steps.continuous - predicted).square().sum(-1).mean()
        if self.discrete_head is not None:
            logits, offset, entropy = self.discrete_head(hidden), 0, 0.0
            for i, size in enumerate(self.branches):
                p = torch.softmax(logits[:, offset : offset + size], dim=-1)
                offset += size
                chosen = p.gather(-1, steps.discrete[:, i : i + 1]).squeeze(-1)
                entropy = entropy - torch.log(chosen + EPSILON)
            loss = loss + entropy.mean()
        return loss

    def update_normalization(self, steps: Transitions) -> None:
        self.body.update_normalization(steps.obs)

    def _device(self) -> torch.device:
        return next(self.parameters()).device

    def state_dict(self, *args: Any, **kwargs: Any) -> dict[str, Any]:
        state = super().state_dict(*args, **kwargs)
        state["updated"] = torch.tensor(self.updated)
        return state

    def load_state_dict(self, state: dict[str, Any], *args: Any, **kwargs: Any) -> Any:
        state = dict(state)
        self.updated = bool(state.pop("updated", torch.tensor(True)))
        return super().load_state_dict(state, *args, **kwargs)
