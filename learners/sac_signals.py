"""A SAC behavior's reward signals besides the extrinsic one (curiosity, RND, GAIL), as
ML-Agents' SAC uses them: each is a reward stream of its own in the Q networks, with
its reward computed on every sampled batch (times its strength), its own gamma, and no
episode end where it ignores them (``ignore_done``); its networks train on sampled
batches of their own, one per ``reward_signal_steps_per_update`` new steps
(``learners/sac.py``)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch
from tensordict import TensorDict

from batches import keys
from learners.policies import ActorCritic
from learners.sac_terms import CONTINUOUS_ACTION, DISCRETE_ACTION
from learners.signal_base import Signal, Transitions
from learners.signals import load_signal_states, signal_states


class SacSignals:
    def __init__(self, network: ActorCritic, items: list[Signal]) -> None:
        """``items``: the behavior's signals (``learners.signals.make_signals``)."""
        self.items = items
        self.names = network.sensor_names
        device = network.value.weight.device
        # each signal's gamma, and whether its stream goes on past an episode's end
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

    def train(self, batches: Iterable[TensorDict]) -> dict[str, float]:
        """One step of every signal's networks per sampled batch: their mean losses, and
        ML-Agents' ``Policy/<Signal> Reward`` (here the mean over the last batch rewarded)."""
        sums: dict[str, float] = {}
        count = 0
        for batch in batches:
            steps, count = self.transitions(batch), count + 1
            for signal in self.items:
                for name, value in signal.update(steps).items():
                    sums[name] = sums.get(name, 0.0) + value
        rewards = self.last_rewards.tolist()
        report = {f"Policy/{s.stat} Reward": r for s, r in zip(self.items, rewards, strict=True)}
        return {name: total / max(count, 1) for name, total in sums.items()} | report

    def state_dict(self) -> list[dict[str, Any]]:
        return signal_states(self.items)

    def load_state_dict(self, state: list[dict[str, Any]]) -> None:
        load_signal_states(self.items, state)
