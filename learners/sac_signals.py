"""A SAC behavior's reward signals besides the extrinsic one (curiosity, RND, GAIL), as
ML-Agents' SAC uses them: each is a reward stream of its own in the Q networks, with
its reward computed on every sampled batch (times its strength), its own gamma, and no
episode end where it ignores them (``ignore_done``); its networks train on sampled
batches of their own, one per ``reward_signal_steps_per_update`` new steps
(``learners/sac.py``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDict

from batches import keys
from batches.expert_steps import ExpertSteps
from learners.policies import ActorCritic
from learners.sac_terms import CONTINUOUS_ACTION, DISCRETE_ACTION
from learners.settings import RewardSignalSettings
from learners.signal_base import Transitions
from learners.signals import load_signal_states, make_signal, signal_states


class SacSignals:
    def __init__(
        self,
        network: ActorCritic,
        settings: tuple[RewardSignalSettings, ...],
        device: torch.device | str = "cpu",
        experts: Mapping[str, ExpertSteps] | None = None,
    ) -> None:
        self.items = [make_signal(network, s, experts or {}).to(device) for s in settings]
        self.names = network.sensor_names
        # each stream's gamma and whether an episode's end stops it (the extrinsic first)
        self.gammas = torch.tensor([s.gamma for s in self.items], device=device)
        self.ignore_done = torch.tensor([s.ignore_done for s in self.items], device=device)
        self.last_rewards = torch.zeros(len(self.items), device=device)  # for the report

    def __len__(self) -> int:
        return len(self.items)

    def transitions(self, batch: TensorDict) -> Transitions:
        """What a signal reads of replayed transitions ``[N]``."""
        nxt = batch[keys.NEXT]
        return Transitions(
            {name: batch[keys.OBS, name] for name in self.names},
            {name: nxt[keys.OBS, name] for name in self.names},
            batch.get(CONTINUOUS_ACTION, None),
            batch.get(DISCRETE_ACTION, None),
            nxt[keys.TERMINATED].reshape(-1),
        )

    def update_normalization(self, batch: TensorDict) -> None:
        steps = self.transitions(batch)
        for signal in self.items:
            signal.update_normalization(steps)

    @torch.no_grad()
    def rewards(self, batch: TensorDict) -> torch.Tensor:
        """Each signal's reward of each transition, times its strength ``[N, signals]``."""
        steps = self.transitions(batch)
        rewards = torch.stack([s.rewards(steps) * s.strength for s in self.items], dim=-1)
        self.last_rewards = rewards.mean(0)
        return rewards

    def train(self, batch: TensorDict) -> dict[str, float]:
        """One step of every signal's networks on a sampled batch; their losses."""
        steps = self.transitions(batch)
        return {k: v for signal in self.items for k, v in signal.update(steps).items()}

    def report(self) -> dict[str, float]:
        """ML-Agents' ``Policy/<Signal> Reward``: here the mean over the last batch."""
        rewards = self.last_rewards.tolist()
        return {f"Policy/{s.stat} Reward": r for s, r in zip(self.items, rewards, strict=True)}

    def state_dict(self) -> list[dict[str, Any]]:
        return signal_states(self.items)

    def load_state_dict(self, state: list[dict[str, Any]]) -> None:
        load_signal_states(self.items, state)
