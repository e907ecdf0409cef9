"""A behavior's reward signals besides the extrinsic one, as PPO (``learners/algorithms/ppo.py``)
uses them in one update: each with a value head of its own on the policy's critic
(``ActorCritic.value_of``'s ``heads``), its rewards on the update's rows before it
trains, its networks trained after its epochs, its TensorBoard figures."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import nn

from batches.expert_steps import ExpertSteps
from learners.algorithms.minibatch import load_optimizer
from learners.algorithms.trajectory_store import Rows
from learners.networks.initializers import xavier
from learners.networks.policies import ActorCritic
from learners.reward_signals.base import Signal, Transitions
from learners.reward_signals.episode_sums import EpisodeSums
from learners.reward_signals.gail import GAIL
from learners.reward_signals.intrinsic import RND, Curiosity
from learners.trainer_config.settings import RewardSignalSettings

CHUNK = 4096  # rows a signal evaluates at once


def make_signal(
    network: ActorCritic, settings: RewardSignalSettings, experts: Mapping[str, ExpertSteps]
) -> Signal:
    """The signal of ``settings``; gail's demonstrations must fit the behavior's spec."""
    if settings.kind == "rnd":
        return RND(network.spec, settings)
    if settings.kind == "curiosity":
        return Curiosity(network.spec, settings)
    demo = experts.get(str(settings.demo_path))
    if demo is None:
        raise ValueError(f"reward_signals.gail: {settings.demo_path} not loaded")
    if problem := demo.problem_with(network.spec):
        raise ValueError(f"reward_signals.gail: {problem}")
    return GAIL(network.spec, settings, demo)


def make_signals(
    network: ActorCritic,
    settings: tuple[RewardSignalSettings, ...],
    device: torch.device | str = "cpu",
    experts: Mapping[str, ExpertSteps] | None = None,
) -> list[Signal]:
    """The signals of ``settings`` on ``device``; ``experts``: gail's, by ``demo_path``."""
    return [make_signal(network, s, experts or {}).to(device) for s in settings]


class Signals:
    """``rewards`` on the update's rows (before it trains), ``train`` beside its epochs,
    then ``report``; ``experts``: gail's demonstrations, by ``demo_path``."""

    def __init__(
        self,
        network: ActorCritic,
        settings: tuple[RewardSignalSettings, ...],
        device: torch.device | str = "cpu",
        experts: Mapping[str, ExpertSteps] | None = None,
    ) -> None:
        self.items = make_signals(network, settings, device, experts)
        width = network.value.in_features
        self.heads = nn.ModuleList(xavier(width, 1) for _ in settings).to(device)
        self._steps: Transitions | None = None
        self._rewards: list[torch.Tensor] = []
        self._episodes = EpisodeSums(len(self.items))
        self._finished = np.zeros((0, len(self.items)))  # this update's ended episodes' sums

    def __len__(self) -> int:
        return len(self.items)

    @property
    def terminal_obs(self) -> bool:
        """Whether a signal reads the observation after an episode's last step: to
        bootstrap its value there (``ignore_done``) or in its networks."""
        return any(s.ignore_done or s.reads_next_obs for s in self.items)

    def rewards(self, rows: Rows) -> list[tuple[torch.Tensor, float, bool]]:
        """Each signal's reward per row (times its strength), gamma and ``ignore_done``."""
        if not self.items:
            return []
        reads_next = any(s.reads_next_obs for s in self.items)
        steps = self._steps = transitions(rows, reads_next)
        for signal in self.items:
            signal.update_normalization(steps)
        self._rewards = [
            torch.cat([s.rewards(steps[i : i + CHUNK]) for i in range(0, len(rows), CHUNK)])
            * s.strength
            for s in self.items
        ]
        assert rows.agent is not None and rows.ended is not None  # a store with episodes
        self._finished = self._episodes.finished(rows.agent, rows.ended, self._rewards)
        return [(r, s.gamma, s.ignore_done) for r, s in zip(self._rewards, self.items, strict=True)]

    def train(
        self,
        train: torch.Tensor,
        num_epoch: int,
        batch_size: int,
        generator: torch.Generator | None = None,
    ) -> dict[str, float]:
        """Each signal's networks: one step per minibatch of the trained rows, as many
        minibatches as PPO's epochs took (the remainder left out); the mean losses. Random
        draws come from ``generator`` (None: the global one)."""
        if self._steps is None:
            return {}
        sums: dict[str, float] = {}
        count = 0
        for _ in range(num_epoch):
            shuffled = torch.randperm(len(train), generator=generator, device=train.device)
            order = train[shuffled]
            for index in order.split(batch_size):
                if len(index) < batch_size:
                    continue
                count += 1
                minibatch = self._steps[index]
                for signal in self.items:
                    for name, value in signal.update(minibatch, generator).items():
                        sums[name] = sums.get(name, 0.0) + value
        self._steps = None
        return {name: total / max(count, 1) for name, total in sums.items()}

    def report(self, value: torch.Tensor, train: torch.Tensor) -> dict[str, float]:
        """ML-Agents' ``Policy/<Signal> Value Estimate`` and ``Policy/<Signal> Reward``:
        the mean strength-weighted sum per episode of the episodes that ended in this
        update (none ended: no reward figure)."""
        out = {}
        for k, signal in enumerate(self.items):
            out[f"Policy/{signal.stat} Value Estimate"] = float(value[train, 1 + k].mean())
            if len(self._finished):
                out[f"Policy/{signal.stat} Reward"] = float(self._finished[:, k].mean())
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"heads": self.heads.state_dict(), "signals": signal_states(self.items)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.heads.load_state_dict(state["heads"])
        load_signal_states(self.items, state["signals"])


def signal_states(items: list[Signal]) -> list[dict[str, Any]]:
    """Each signal's networks and optimizer, for a checkpoint."""
    return [{"networks": s.state_dict(), "optimizer": s.optimizer.state_dict()} for s in items]


def load_signal_states(items: list[Signal], saved: list[dict[str, Any]]) -> None:
    for signal, state in zip(items, saved, strict=True):
        signal.load_state_dict(state["networks"])
        load_optimizer(signal.optimizer, state["optimizer"])  # stays fused


def transitions(rows: Rows, next_obs_too: bool = True) -> Transitions:
    """Every row's observation, next observation (unless no signal reads it: a copy of
    the buffer's observations) and action: a row's next observation is the next row's,
    or at a trajectory's end the one the store kept there."""
    next_obs = {}
    for name, obs in rows.obs.items() if next_obs_too else ():
        after = torch.empty_like(obs)
        after[:-1] = obs[1:]
        after[rows.end_rows] = rows.end_obs[name]
        next_obs[name] = after
    # episode ends: the terminated ones (an end at max_step looks like a horizon cut here)
    return Transitions(rows.obs, next_obs, rows.continuous, rows.discrete, rows.terminated)
