"""Per-episode sums of rewards that only the learner computes (curiosity, RND, GAIL), as
ML-Agents reports ``Policy/<Signal> Reward``: each agent's rewards summed from its
episode's first step to its last, over as many updates as the episode spans; one figure
per finished episode.

An update's rows are packed trajectory pieces; an agent's pieces come in the order it
lived them (one worker collects each agent). Where an episode ends is ``Rows.ended``
(``done`` and not a cut); an agent's unfinished episode carries into the next update.
"""

from __future__ import annotations

from collections import OrderedDict
from itertools import pairwise

import numpy as np
import torch
from tensordict import TensorDictBase

from batches import keys

CARRIED_EPISODES = 65_536  # unfinished episodes kept between updates (agents mid-episode)


def agent_key(segment: TensorDictBase) -> torch.Tensor:
    """Each step's agent ``[N]``, unique across workers (worker and Unity id in one int64)."""
    worker = segment.get(keys.WORKER, torch.zeros_like(segment[keys.AGENT_ID]))
    return worker * 2**32 + segment[keys.AGENT_ID]


def episode_ended(segment: TensorDictBase) -> torch.Tensor:
    """Where an agent's episode ended ``[N]``: ``done`` and not a cut mid-episode."""
    done = segment[keys.NEXT, keys.DONE].reshape(-1)
    cut = segment.get((keys.NEXT, keys.CUT), None)
    return done if cut is None else done & ~cut.reshape(-1)


class EpisodeSums:
    """Sums of ``k`` reward streams per agent's episode."""

    def __init__(self, streams: int, carried: int = CARRIED_EPISODES) -> None:
        self.streams = streams
        self.carried = carried
        self._open: OrderedDict[int, np.ndarray] = OrderedDict()  # agent -> sums so far

    def finished(
        self, agent: torch.Tensor, ended: torch.Tensor, rewards: list[torch.Tensor]
    ) -> np.ndarray:
        """The sums ``[episodes, k]`` of the episodes that ended in these rows (in no
        particular order); the rest is kept for the agents' next rows."""
        agents = agent.cpu().numpy()
        ends = ended.cpu().numpy().astype(bool)
        values = torch.stack([r.reshape(-1) for r in rewards], dim=1).double().cpu().numpy()
        order = np.argsort(agents, kind="stable")  # each agent's rows together, in order
        agents, ends, values = agents[order], ends[order], values[order]
        bounds = np.flatnonzero(np.r_[True, agents[1:] != agents[:-1], True])
        done: list[np.ndarray] = []
        for start, stop in pairwise(bounds):
            key = int(agents[start])
            total = np.cumsum(values[start:stop], axis=0)
            before = self._open.pop(key, np.zeros(self.streams))  # its episode so far
            last = -1
            for end in np.flatnonzero(ends[start:stop]):
                done.append(before + total[end] - (total[last] if last >= 0 else 0.0))
                before, last = np.zeros(self.streams), end
            if last < stop - start - 1:  # goes on in a later update
                self._open[key] = before + total[-1] - (total[last] if last >= 0 else 0.0)
        while len(self._open) > self.carried:
            self._open.popitem(last=False)  # the agent longest unseen: it left
        return np.array(done).reshape(-1, self.streams)
