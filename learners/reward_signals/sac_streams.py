"""A SAC behavior's reward signals besides the extrinsic one (curiosity, RND, GAIL), as
ML-Agents' SAC uses them: each is a reward stream of its own in the Q networks, with
its reward computed on every sampled batch (times its strength), its own gamma, and no
episode end where it ignores them (``ignore_done``); its networks train on sampled
batches of their own, one per ``reward_signal_steps_per_update`` new steps
(``learners/algorithms/sac.py``). For the report, as ML-Agents' SAC does, each signal also rewards
the steps as they arrive, summed per agent's episode (``Policy/<Signal> Reward``)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from batches import keys
from learners.algorithms.sac_terms import CONTINUOUS_ACTION, DISCRETE_ACTION
from learners.networks.policies import ActorCritic
from learners.reward_signals.base import Signal, Transitions
from learners.reward_signals.episode_sums import EpisodeSums, agent_key, episode_ended
from learners.reward_signals.ppo_streams import load_signal_states, signal_states


class SacSignals:
    def __init__(self, network: ActorCritic, items: list[Signal]) -> None:
        """``items``: the behavior's signals
        (``learners.reward_signals.ppo_streams.make_signals``)."""
        self.items = items
        self.names = network.sensor_names
        device = network.value.weight.device
        # each signal's gamma, and whether its stream goes on past an episode's end
        self.gammas = torch.tensor([s.gamma for s in self.items], device=device)
        self.ignore_done = torch.tensor([s.ignore_done for s in self.items], device=device)
        self._episodes = EpisodeSums(len(self.items))
        self._finished: list[np.ndarray] = []  # sums of the episodes ended since the report

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
        return torch.stack([s.rewards(steps) * s.strength for s in self.items], dim=-1)

    def observe(self, batch: TensorDict, segment: TensorDict) -> None:
        """Arriving transitions (``batch``, of ``segment``): their rewards added to each
        agent's episode, as ML-Agents' SAC evaluates every trajectory for its report."""
        rewards = self.rewards(batch)
        ended = self._episodes.finished(
            agent_key(segment), episode_ended(segment), list(rewards.unbind(-1))
        )
        if len(ended):
            self._finished.append(ended)

    def train(self, batches: Iterable[TensorDict]) -> dict[str, float]:
        """One step of every signal's networks per sampled batch: their mean losses, and
        ML-Agents' ``Policy/<Signal> Reward``: the mean sum per episode over the episodes
        that ended since the last report (none ended: not reported)."""
        sums: dict[str, float] = {}
        count = 0
        for batch in batches:
            steps, count = self.transitions(batch), count + 1
            for signal in self.items:
                for name, value in signal.update(steps).items():
                    sums[name] = sums.get(name, 0.0) + value
        report: dict[str, float] = {}
        if self._finished:
            means = np.concatenate(self._finished).mean(0)
            stats = [f"Policy/{s.stat} Reward" for s in self.items]
            report = dict(zip(stats, means.tolist(), strict=True))
            self._finished = []
        return {name: total / max(count, 1) for name, total in sums.items()} | report

    def state_dict(self) -> list[dict[str, Any]]:
        return signal_states(self.items)

    def load_state_dict(self, state: list[dict[str, Any]]) -> None:
        load_signal_states(self.items, state)
