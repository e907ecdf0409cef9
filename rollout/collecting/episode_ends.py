"""The agents' episodes that ended, as a segment builder records them for the metrics:
ML-Agents' ``Environment/Cumulative Reward``, ``Environment/Episode Length``,
``Policy/Extrinsic Reward`` and ``Environment/Group Cumulative Reward`` come from them."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class EpisodeEnds(NamedTuple):
    """Agents' episodes that ended: each one's return, length in decisions, and the group
    rewards and groupmates' rewards it got (ML-Agents' ``Policy/Extrinsic Reward`` adds the
    group rewards; POCA's, the groupmates' rewards too)."""

    returns: np.ndarray
    lengths: np.ndarray
    group_rewards: np.ndarray
    mates_rewards: np.ndarray


class EpisodeLog:
    """Episodes ended since the metrics last drained them (batches, one per exchange)."""

    def __init__(self) -> None:
        self._ended: list[np.ndarray] = []  # [k, 4]: EpisodeEnds' columns
        # group rewards of grouped agents' episodes that ended with their group (ML-Agents'
        # "Environment/Group Cumulative Reward"; a sacrificed agent's is not counted)
        self._with_group: list[np.ndarray] = []

    def add(self, ended: EpisodeEnds, with_group: np.ndarray) -> None:
        """One exchange's ended episodes; ``with_group``: those that ended with their group."""
        self._ended.append(np.stack(ended, axis=1).astype(np.float64))
        if with_group.any():
            self._with_group.append(ended.group_rewards[with_group].astype(np.float64))

    def drain(self) -> EpisodeEnds:
        """The episodes ended since the last call."""
        ended, self._ended = self._ended, []
        table = np.concatenate(ended) if ended else np.zeros((0, 4))
        return EpisodeEnds(table[:, 0], table[:, 1].astype(np.int64), table[:, 2], table[:, 3])

    def drain_group(self) -> np.ndarray:
        """Group rewards of the grouped episodes that ended with their group since the last
        call."""
        episodes, self._with_group = self._with_group, []
        return np.concatenate(episodes) if episodes else np.zeros(0)
