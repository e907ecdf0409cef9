"""GridWorld: reach the goal of the colour the goal signal names (the ML-Agents example, batched).

Nine areas, one agent each (``num_areas`` multiplies). At every episode begin an area places
the agent, ``numGreenGoals`` green goals and ``numRedGoals`` red goals (defaults 1 and 1) on
distinct random cells of a ``gridSize`` x ``gridSize`` grid (default 5), and picks which colour
is correct this episode. The agent sees a top-down camera image (``CameraSensor``, RGB PNG,
(3, 40, 40)): the grid with a grey wall border, scaled to fill the image, black floor, the
agent blue, green goals green and red goals red; and a goal signal (``GoalSignal``,
GOAL_SIGNAL, one-hot: [green, red]).

Actions are one branch of 5 (0 none, 1 up, 2 down, 3 left, 4 right; up is towards image row
0) with masking on, as in the example: moves into the walls are masked (True = forbidden) and,
if sent anyway, leave the agent in place. Every step costs -0.01; stepping onto a goal ends the
episode with ``SetReward`` +1 for the correct colour and -1 for the wrong one. MaxStep 100
(interrupted). The agent asks for a decision every step and keeps its id across episodes.
The real camera resolution is unverified; the image here is sized for a small CNN.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from unitysim.envs.base import (
    GOAL_SIGNAL,
    Actions,
    AgentInfos,
    Behavior,
    Output,
    Parameters,
    Sensor,
    SimEnv,
)

IMAGE = 40  # pixels per side
MAX_GRID = IMAGE - 2  # every cell, walls included, keeps at least one pixel
MAX_STEP = 100
STEP_REWARD = -0.01

FLOOR, WALL, GREEN, RED, AGENT = 0, 1, 2, 3, 4
# Colours as k/255 so that PNG encoding is lossless.
PALETTE = np.array(
    [[0, 0, 0], [128, 128, 128], [0, 255, 0], [255, 0, 0], [0, 0, 255]], dtype=np.float32
) / np.float32(255.0)
PALETTE_CHANNELS = np.ascontiguousarray(PALETTE.T)  # (3, codes)
# (row, column) change per action: none, up, down, left, right
MOVES = np.array([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]], dtype=np.int64)


class GridWorld(SimEnv):
    name = "GridWorld"
    behaviors = (
        Behavior(
            "GridWorld?team=0",
            (
                Sensor.camera("CameraSensor", 3, IMAGE, IMAGE),
                Sensor.vector("GoalSignal", 2, observation_type=GOAL_SIGNAL),
            ),
            branches=(5,),
        ),
    )
    agents_per_area = 9

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        n = self.agents_per_area * self.num_areas
        self.ids = np.arange(n, dtype=np.int32)
        side = MAX_GRID + 2
        self.cells = np.full((n, side, side), WALL, dtype=np.intp)  # walls and goals, padded
        self.size = np.full(n, 5, dtype=np.int64)  # grid size of each agent's area
        self.pos = np.zeros((n, 2), dtype=np.int64)  # agent (row, column) inside the walls
        self.target = np.zeros(n, dtype=np.int64)  # correct colour: 0 green, 1 red
        self.episode_steps = np.zeros(n, dtype=np.int64)
        self.rows = np.arange(n)

    # --- episode handling ------------------------------------------------------------

    def _begin_episodes(self, which: np.ndarray) -> None:
        """``AreaReset`` and ``OnEpisodeBegin``: a fresh layout and a fresh correct colour."""
        k = int(which.sum())
        if k == 0:
            return
        size = int(np.clip(round(self.params.get("gridSize", 5.0)), 2, MAX_GRID))
        green = max(int(self.params.get("numGreenGoals", 1.0)), 0)
        red = max(int(self.params.get("numRedGoals", 1.0)), 0)
        goals = min(green + red, size * size - 1)
        green = min(green, goals)
        red = goals - green

        index = np.flatnonzero(which)
        self.size[index] = size
        self.cells[index] = WALL
        self.cells[index, 1 : size + 1, 1 : size + 1] = FLOOR
        places = self.rng.random((k, size * size)).argsort(axis=1)[:, : 1 + goals]
        row, col = np.divmod(places, size)
        self.pos[index] = np.column_stack([row[:, 0], col[:, 0]])
        codes = np.array([GREEN] * green + [RED] * red, dtype=np.intp)
        self.cells[index[:, None], row[:, 1:] + 1, col[:, 1:] + 1] = codes
        colours = self.rng.integers(0, 2, size=k)
        if green == 0 or red == 0:
            colours[:] = 1 if green == 0 and red > 0 else 0
        self.target[index] = colours
        self.episode_steps[index] = 0

    def _observe(self, which: np.ndarray) -> list[np.ndarray]:
        """Camera images (CHW, in [0, 1]) and goal signals of the agents ``which`` (indices)."""
        n, side = len(which), self.cells.shape[1]
        span = self.size[which, None] + 2  # cells per image side, walls included
        pixel = (np.arange(IMAGE)[None, :] * span) // IMAGE  # (n, IMAGE): cell of each pixel
        flat = (which[:, None, None] * side + pixel[:, :, None]) * side + pixel[:, None, :]
        codes = np.take(self.cells, flat)  # (n, IMAGE, IMAGE)
        on_agent = (pixel == self.pos[which, 0:1] + 1)[:, :, None] & (
            pixel == self.pos[which, 1:2] + 1
        )[:, None, :]
        codes[on_agent] = AGENT
        image = np.take(PALETTE_CHANNELS, codes, axis=1).transpose(1, 0, 2, 3)
        signal = np.zeros((n, 2), dtype=np.float32)
        signal[np.arange(n), self.target[which]] = 1.0
        return [image, signal]

    def _masks(self, which: np.ndarray) -> np.ndarray:
        row, col, last = self.pos[which, 0], self.pos[which, 1], self.size[which] - 1
        none = np.zeros(len(row), dtype=bool)
        return np.column_stack([none, row == 0, row == last, col == 0, col == last])

    def _infos(
        self, which: np.ndarray, reward: np.ndarray, **kwargs: np.ndarray | bool
    ) -> AgentInfos:
        return AgentInfos.build(
            self.ids[which], self._observe(which), reward, action_mask=self._masks(which), **kwargs
        )

    # --- the contract ----------------------------------------------------------------

    def reset(self) -> Output:
        everyone = np.ones(len(self.ids), dtype=bool)
        self._begin_episodes(everyone)
        infos = self._infos(self.rows, np.zeros(len(self.ids), dtype=np.float32))
        return {self.behaviors[0].name: infos}

    def step(self, actions: Mapping[str, Actions]) -> Output:
        behavior = self.behaviors[0].name
        action = np.zeros(len(self.ids), dtype=np.int64)
        if behavior in actions and len(actions[behavior]):
            # Decisions are always for every agent, in id order.
            action[:] = np.clip(actions[behavior].discrete[:, 0], 0, 4)
        moved = self.pos + MOVES[action]
        inside = ((moved >= 0) & (moved < self.size[:, None])).all(axis=1)
        self.pos = np.where(inside[:, None], moved, self.pos)
        self.episode_steps += 1

        code = self.cells[self.rows, self.pos[:, 0] + 1, self.pos[:, 1] + 1]
        at_goal = (code == GREEN) | (code == RED)
        correct = at_goal & ((code == RED) == (self.target == 1))
        reward = np.where(at_goal, np.where(correct, 1.0, -1.0), STEP_REWARD).astype(np.float32)
        interrupted = ~at_goal & (self.episode_steps >= MAX_STEP)
        done = at_goal | interrupted
        if not done.any():
            return {behavior: self._infos(self.rows, reward)}

        ended = np.flatnonzero(done)
        terminal = self._infos(ended, reward[ended], done=True, max_step_reached=interrupted[ended])
        self._begin_episodes(done)
        reward[done] = 0.0
        return {behavior: AgentInfos.concat([terminal, self._infos(self.rows, reward)])}
