"""Basic: walk along a line of 20 cells to the small or the large goal (the ML-Agents example).

Follows ``BasicController``: the agent starts at position 10 and moves by one cell per decision
(branch of 3: 0 stay, 1 left, 2 right), within positions 0..19. Each move costs -0.01; reaching
the small goal (7) adds +0.1 and reaching the large goal (17) adds +1.0, and either ends the
episode. There is no MaxStep. The observation is the one-hot of the position (sensor "Basic",
shape (20,)), and the agent asks for a decision every step.

The example resets its agent by disabling and re-enabling it, so every episode is played by a
NEW agent id: the reference notes that Basic "adds new agents during a run". Here the terminal
info carries the old id and, in the same message, the next decision carries an id from a
counter that never repeats (also across ``reset``). The best return is 7 * -0.01 + 1 = 0.93,
the example's benchmark. ``num_areas`` gives that many independent agents.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from unitysim.envs.base import Actions, AgentInfos, Behavior, Output, Parameters, Sensor, SimEnv

EXTENT = 20  # positions 0..19, the size of the one-hot
START = 10
SMALL_GOAL, SMALL_REWARD = 7, 0.1
LARGE_GOAL, LARGE_REWARD = 17, 1.0
STEP_REWARD = -0.01
MOVES = np.array([0, -1, 1], dtype=np.int64)  # stay, left, right


class Basic(SimEnv):
    name = "Basic"
    behaviors = (Behavior("Basic?team=0", (Sensor.vector("Basic", EXTENT),), branches=(3,)),)
    agents_per_area = 1

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        n = self.agents_per_area * self.num_areas
        self.next_id = 0
        self.ids = np.zeros(n, dtype=np.int32)
        self.position = np.full(n, START, dtype=np.int64)
        self.mask = np.zeros((n, 3), dtype=bool)  # nothing is ever masked

    def _begin_episodes(self, which: np.ndarray) -> None:
        """``ResetAgent``: back to the start, as a re-enabled agent with a new id."""
        k = int(which.sum())
        self.ids[which] = np.arange(self.next_id, self.next_id + k, dtype=np.int32)
        self.next_id += k
        self.position[which] = START

    def _observe(self) -> np.ndarray:
        obs = np.zeros((len(self.position), EXTENT), dtype=np.float32)
        obs[np.arange(len(self.position)), self.position] = 1.0
        return obs

    def reset(self) -> Output:
        self._begin_episodes(np.ones(len(self.ids), dtype=bool))
        infos = AgentInfos.build(self.ids, [self._observe()], action_mask=self.mask)
        return {self.behaviors[0].name: infos}

    def step(self, actions: Mapping[str, Actions]) -> Output:
        behavior = self.behaviors[0].name
        action = np.zeros(len(self.ids), dtype=np.int64)
        if behavior in actions and len(actions[behavior]):
            # Decisions are always for every agent, in the order last reported.
            action[:] = np.clip(actions[behavior].discrete[:, 0], 0, 2)
        self.position = np.clip(self.position + MOVES[action], 0, EXTENT - 1)
        small, large = self.position == SMALL_GOAL, self.position == LARGE_GOAL
        reward = np.full(len(self.ids), STEP_REWARD, dtype=np.float32)
        reward += np.where(small, np.float32(SMALL_REWARD), np.float32(0.0))
        reward += np.where(large, np.float32(LARGE_REWARD), np.float32(0.0))
        done = small | large
        if not done.any():
            infos = AgentInfos.build(self.ids, [self._observe()], reward, action_mask=self.mask)
            return {behavior: infos}
        terminal = AgentInfos.build(
            self.ids[done],
            [self._observe()[done]],
            reward=reward[done],
            done=True,
            action_mask=self.mask[done],
        )
        self._begin_episodes(done)
        reward[done] = 0.0  # the new agents have earned nothing yet
        decisions = AgentInfos.build(self.ids, [self._observe()], reward, action_mask=self.mask)
        return {behavior: AgentInfos.concat([terminal, decisions])}
