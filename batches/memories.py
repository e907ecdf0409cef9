"""Each agent's recurrent memory between its decisions, on the acting side.

A policy with ``network_settings.memory`` reads the memory its LSTM left at the agent's
last decision, however many exchanges ago that was (agents that request decisions every
few steps keep theirs across the gap), and starts from zeros at an episode's start, as
ML-Agents' policy keeps ``memory_dict`` by agent id. Plain numpy: workers carry no torch.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

KEPT = 65_536  # agents remembered at most: one that vanished without an episode end goes


class AgentMemories:
    """Memories ``[memory_size]`` by agent id; an agent never seen (or forgotten) has zeros."""

    def __init__(self, size: int, kept: int = KEPT) -> None:
        self.size, self.kept = size, kept
        self._by_agent: OrderedDict[int, np.ndarray] = OrderedDict()  # least recent first

    def __len__(self) -> int:
        return len(self._by_agent)

    def get(self, agents: np.ndarray) -> np.ndarray:
        """``[n, size]`` float32: each agent's memory, zeros for one without."""
        out = np.zeros((len(agents), self.size), np.float32)
        for row, agent in enumerate(agents.tolist()):
            if (memory := self._by_agent.get(agent)) is not None:
                out[row] = memory
        return out

    def put(self, agents: np.ndarray, memories: np.ndarray) -> None:
        for agent, memory in zip(agents.tolist(), memories, strict=True):
            self._by_agent[agent] = memory
            self._by_agent.move_to_end(agent)
        while len(self._by_agent) > self.kept:
            self._by_agent.popitem(last=False)

    def forget(self, agents: np.ndarray) -> None:
        """Agents whose episode ended: their next decision starts from zeros."""
        for agent in agents.tolist():
            self._by_agent.pop(agent, None)

    def clear(self) -> None:
        """Unity restarted: every episode starts anew."""
        self._by_agent.clear()
