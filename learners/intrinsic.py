"""Intrinsic reward signals beside the extrinsic one, as ML-Agents' reward providers
compute and train them: ``rnd`` (random network distillation) and ``curiosity`` (the
intrinsic curiosity module). PPO (``learners/ppo.py``) gives each signal a value head of
its own on the critic and a GAE with its own gamma, sums the signals' advantages, and
trains each signal's networks once per minibatch of its update.

Each signal's networks follow its own ``network_settings``: the same encoders and MLP
body as a policy's (``learners/policies.py``'s ``ActorCritic``, whose trunk is
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

import math
from dataclasses import dataclass
from typing import Any

import torch
from mlagents_envs.base_env import BehaviorSpec
from torch import nn

from learners.policies import ActorCritic
from learners.settings import NetworkSettings, RewardSignalSettings
from learners.trajectory_store import Rows

EPSILON = 1e-10


@dataclass(frozen=True)
class Transitions:
    """What a signal reads of some steps: observations, the next ones, the actions."""

    obs: dict[str, torch.Tensor]
    next_obs: dict[str, torch.Tensor]
    continuous: torch.Tensor | None  # as stored: the Gaussian's sample
    discrete: torch.Tensor | None

    def __getitem__(self, index: torch.Tensor) -> Transitions:
        def pick(tensor: torch.Tensor | None) -> torch.Tensor | None:
            return None if tensor is None else tensor[index]

        return Transitions(
            {n: o[index] for n, o in self.obs.items()},
            {n: o[index] for n, o in self.next_obs.items()},
            pick(self.continuous),
            pick(self.discrete),
        )


class Body(nn.Module):
    """Encoders and MLP of ``settings``: ML-Agents' ``NetworkBody`` (features only; the
    heads and critic of the ``ActorCritic`` it is built as stay unused)."""

    def __init__(self, spec: BehaviorSpec, settings: NetworkSettings) -> None:
        super().__init__()
        self.network = ActorCritic(spec, settings)
        self.width = settings.hidden_units

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.network.features(obs)

    def trained(self) -> list[nn.Parameter]:
        return [*self.network.encoders.parameters(), *self.network.trunk.parameters()]

    def update_normalization(self, obs: dict[str, torch.Tensor]) -> None:
        self.network.update_normalization(obs)


def _kaiming(fan_in: int, out: int) -> nn.Linear:
    layer = nn.Linear(fan_in, out)
    nn.init.normal_(layer.weight, 0.0, 1.0 / math.sqrt(fan_in))
    nn.init.zeros_(layer.bias)
    return layer


def _xavier(fan_in: int, out: int) -> nn.Linear:
    layer = nn.Linear(fan_in, out)
    nn.init.xavier_uniform_(layer.weight)
    nn.init.zeros_(layer.bias)
    return layer


class Signal(nn.Module):
    """What PPO needs of a signal; ``stat`` is ML-Agents' name in its TensorBoard tags."""

    stat = ""

    def __init__(self, settings: RewardSignalSettings) -> None:
        super().__init__()
        self.settings = settings
        self.gamma, self.strength = settings.gamma, settings.strength

    def rewards(self, steps: Transitions) -> torch.Tensor:
        raise NotImplementedError

    def update(self, steps: Transitions) -> dict[str, float]:
        raise NotImplementedError

    def update_normalization(self, steps: Transitions) -> None:
        raise NotImplementedError

    def _step(self, loss: torch.Tensor) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()


class RND(Signal):
    stat = "Rnd"

    def __init__(self, spec: BehaviorSpec, settings: RewardSignalSettings) -> None:
        super().__init__(settings)
        self.target = Body(spec, settings.network_settings).requires_grad_(False)
        self.predictor = Body(spec, settings.network_settings)
        self.optimizer = torch.optim.Adam(self.predictor.trained(), settings.learning_rate)

    def _error(self, steps: Transitions) -> torch.Tensor:
        with torch.no_grad():
            target = self.target(steps.obs)
        return (self.predictor(steps.obs) - target).square().sum(-1)

    def rewards(self, steps: Transitions) -> torch.Tensor:
        with torch.no_grad():
            return self._error(steps)

    def update(self, steps: Transitions) -> dict[str, float]:
        loss = self._error(steps).mean()
        self._step(loss)
        return {"Losses/RND Loss": float(loss.detach())}

    def update_normalization(self, steps: Transitions) -> None:
        self.target.update_normalization(steps.obs)
        self.predictor.update_normalization(steps.obs)


class Curiosity(Signal):
    stat = "Curiosity"
    FORWARD_WEIGHT, LOSS_MULTIPLIER, HIDDEN = 0.2, 10.0, 256

    def __init__(self, spec: BehaviorSpec, settings: RewardSignalSettings) -> None:
        super().__init__(settings)
        self.body = Body(spec, settings.network_settings)
        width, actions = self.body.width, spec.action_spec
        self.continuous = actions.continuous_size
        self.branches = tuple(actions.discrete_branches)
        flat = self.continuous + sum(self.branches)
        self.inverse = nn.Sequential(_kaiming(2 * width, self.HIDDEN), nn.SiLU())
        self.continuous_head = _xavier(self.HIDDEN, self.continuous) if self.continuous else None
        self.discrete_head = _xavier(self.HIDDEN, sum(self.branches)) if self.branches else None
        self.forward_model = nn.Sequential(
            _kaiming(width + flat, self.HIDDEN), nn.SiLU(), _xavier(self.HIDDEN, width)
        )
        models = (self.inverse, self.continuous_head, self.discrete_head, self.forward_model)
        trained = [p for m in models if m is not None for p in m.parameters()]
        self.optimizer = torch.optim.Adam([*self.body.trained(), *trained], settings.learning_rate)
        self.updated = False

    def _flat_actions(self, steps: Transitions) -> torch.Tensor:
        parts = []
        if self.continuous:
            assert steps.continuous is not None
            parts.append(steps.continuous)
        if self.branches:
            assert steps.discrete is not None
            parts += [
                nn.functional.one_hot(steps.discrete[:, i], size).float()
                for i, size in enumerate(self.branches)
            ]
        return torch.cat(parts, dim=-1)

    def _forward_error(
        self, state: torch.Tensor, after: torch.Tensor, steps: Transitions
    ) -> torch.Tensor:
        predicted = self.forward_model(torch.cat([state, self._flat_actions(steps)], dim=-1))
        return 0.5 * (after - predicted).square().sum(-1)

    def rewards(self, steps: Transitions) -> torch.Tensor:
        if not self.updated:
            return torch.zeros(len(next(iter(steps.obs.values()))), device=self._device())
        with torch.no_grad():
            error = self._forward_error(self.body(steps.obs), self.body(steps.next_obs), steps)
        return error.clamp(max=1.0 / self.strength) if self.strength else error

    def update(self, steps: Transitions) -> dict[str, float]:
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


SIGNALS = {"rnd": RND, "curiosity": Curiosity}
CHUNK = 4096  # rows a signal evaluates at once


class Signals:
    """A behavior's intrinsic signals, each with its value head on the policy's critic
    (``value_of``'s ``heads``), as PPO uses them in one update: ``rewards`` on the
    update's rows (before it trains), ``train`` after its epochs, then ``report``."""

    def __init__(
        self,
        network: ActorCritic,
        settings: tuple[RewardSignalSettings, ...],
        device: torch.device | str = "cpu",
    ) -> None:
        self.items = [SIGNALS[s.kind](network.spec, s).to(device) for s in settings]
        width = network.value.in_features
        self.heads = nn.ModuleList(_xavier(width, 1) for _ in settings).to(device)
        self._steps: Transitions | None = None
        self._rewards: list[torch.Tensor] = []

    def __len__(self) -> int:
        return len(self.items)

    def rewards(self, rows: Rows) -> list[tuple[torch.Tensor, float]]:
        """Each signal's reward per row (times its strength) and its gamma."""
        if not self.items:
            return []
        steps = self._steps = transitions(rows)
        for signal in self.items:
            signal.update_normalization(steps)
        self._rewards = [
            torch.cat([s.rewards(steps[i : i + CHUNK]) for i in range(0, len(rows), CHUNK)])
            * s.strength
            for s in self.items
        ]
        return [(r, s.gamma) for r, s in zip(self._rewards, self.items, strict=True)]

    def train(self, train: torch.Tensor, num_epoch: int, batch_size: int) -> dict[str, float]:
        """Each signal's networks: one step per minibatch of the trained rows, as many
        minibatches as PPO's epochs took (the remainder left out); the mean losses."""
        if self._steps is None:
            return {}
        sums: dict[str, float] = {}
        count = 0
        for _ in range(num_epoch):
            order = train[torch.randperm(len(train), device=train.device)]
            for index in order.split(batch_size):
                if len(index) < batch_size:
                    continue
                count += 1
                minibatch = self._steps[index]
                for signal in self.items:
                    for name, value in signal.update(minibatch).items():
                        sums[name] = sums.get(name, 0.0) + value
        self._steps = None
        return {name: total / max(count, 1) for name, total in sums.items()}

    def report(self, value: torch.Tensor, train: torch.Tensor) -> dict[str, float]:
        """ML-Agents' ``Policy/<Signal> Value Estimate`` and ``Policy/<Signal> Reward``;
        the reward here is the mean per trained step (ML-Agents: per episode)."""
        out = {}
        for k, (signal, reward) in enumerate(zip(self.items, self._rewards, strict=True)):
            out[f"Policy/{signal.stat} Value Estimate"] = float(value[train, 1 + k].mean())
            out[f"Policy/{signal.stat} Reward"] = float(reward[train].mean())
        return out

    def state_dict(self) -> dict[str, Any]:
        return {
            "heads": self.heads.state_dict(),
            "signals": [
                {"networks": s.state_dict(), "optimizer": s.optimizer.state_dict()}
                for s in self.items
            ],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.heads.load_state_dict(state["heads"])
        for signal, saved in zip(self.items, state["signals"], strict=True):
            signal.load_state_dict(saved["networks"])
            signal.optimizer.load_state_dict(saved["optimizer"])


def transitions(rows: Rows) -> Transitions:
    """Every row's observation, next observation and action: a row's next observation is
    the next row's, or at a trajectory's end the one the store kept there."""
    next_obs = {}
    for name, obs in rows.obs.items():
        after = torch.empty_like(obs)
        after[:-1] = obs[1:]
        after[rows.end_rows] = rows.end_obs[name]
        next_obs[name] = after
    return Transitions(rows.obs, next_obs, rows.continuous, rows.discrete)
