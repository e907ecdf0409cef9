"""GridFoodCollector and VisualFoodCollector: eat the good food, avoid the poison, freeze
rivals (spec-faithful).

Four 40 x 40 fields with five agents each (ids 0..19, no groups) and 20 pieces of food and
10 of poison per field. Touching food gives +1, poison -1; the piece reappears elsewhere.
The discrete branch is the laser (0 off, 1 on): while on, it freezes every other agent
within 20 ahead (times the ``laser_length`` parameter, 1) and 1 to either side for 4 s
(frozen agents neither move, eat nor shoot; firing the laser while frozen is masked).
Actions are hybrid as in the dump: 3 continuous (forward, right, turn left, in [-1, 1])
plus that branch. Every agent's episode ends at MaxStep 2500 (interrupted), all at once,
so terminal and next decision share a message; then the field's food is laid out anew.

The one sensor is the example's GridSensor-OneHot: 40 x 40 cells of 1 around the agent,
turned with it (row 0 is 20 ahead, column 0 is 20 to the left), channels food, agent,
wall, poison and frozen agent, one-hot per cell (empty cells all 0); outside the field is
wall. It is (5, 40, 40) with dimension properties (1, 2, 2), sent PNG-compressed as release
21's ``FoodCollectorArea`` prefab sets it (``m_CompressionType`` 1): two PNGs an agent, the
second padded, which mlagents-envs cuts back to five channels. Encoding 20 agents' grids
takes about 3.4 ms a step against 0.8 ms for copying the floats, and is 76 times smaller.

**VisualFoodCollector** plays the same rules with the sensors of release 21's
``VisualFoodCollectorArea`` prefab: two fields of four agents (ids 0..7), each seeing an
84 x 84 RGB ``CameraSensor`` (first person, 60° field of view, a PNG) and a
``VectorSensor_size1``, its frozen flag (``useVectorFrozenFlag``). The camera shows the
walls, green food, red poison and the other agents, blue or, frozen, white. The real area
is larger (food spawned within 45 of its centre, 25 pieces of each kind); the stand-in
keeps GridFoodCollector's field.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import FAR, ArenaEnv, drive, limits, steer, uniform_in
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor
from unitysim.envs.perception import FirstPerson, colours, palette

HALF = (20.0, 20.0)
AGENTS = 5
FOOD, POISON = 20, 10
RADIUS = 0.5
SPEED = 5.0
LIMITS = limits(HALF, RADIUS)
FREEZE = 200  # physics steps
MAX_STEP = 2500
GRID = 40
FOOD_TAG, AGENT_TAG, WALL_TAG, POISON_TAG, FROZEN_TAG = range(5)
KIND = np.array([FOOD_TAG] * FOOD + [POISON_TAG] * POISON)
VALUE = np.where(KIND == FOOD_TAG, 1.0, -1.0)
AHEAD = (GRID / 2 - 0.5 - np.arange(GRID)).astype(np.float32)  # cell centres, agent frame
LEFT = (GRID / 2 - 0.5 - np.arange(GRID)).astype(np.float32)


class GridFoodCollector(ArenaEnv):
    name = "GridFoodCollector"
    behaviors = (
        Behavior(
            "GridFoodCollector?team=0",
            (Sensor.visual("GridSensor-OneHot", 5, GRID, GRID),),
            continuous=3,
            branches=(2,),
        ),
    )
    fields_per_area = 4
    layout = ((0, 0),) * AGENTS

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.per_field = len(self.layout)
        self.laser = np.zeros(self.n, dtype=bool)
        self.frozen = np.zeros(self.n, dtype=np.int64)  # physics steps left frozen
        self.food = np.zeros((self.fields, len(KIND), 2))
        self.beam = 20.0  # laser range

    def _begin(self, which: np.ndarray) -> None:
        """Agents of a field begin together (they only end at MaxStep): new places, new food."""
        k = int(which.sum())
        self.beam = 20.0 * self.params.get("laser_length", 1.0)
        self.pos[which] = uniform_in(self.rng, k, HALF, 1.0)
        self.heading[which] = self.rng.uniform(-np.pi, np.pi, k)
        self.motion[which] = 0.0
        self.turn[which] = 0.0
        self.laser[which] = False
        self.frozen[which] = 0
        fields = np.unique(self.field[which])
        self.food[fields] = uniform_in(self.rng, len(fields) * len(KIND), HALF, 1.0).reshape(
            len(fields), len(KIND), 2
        )

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        c = np.clip(actions.continuous, -1.0, 1.0).astype(np.float64)  # forward, right, turn
        self.motion[rows], self.turn[rows] = steer(c[:, 0], c[:, 1], c[:, 2], SPEED, np.pi)
        self.laser[rows] = actions.discrete[:, 0] == 1

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        active = self.frozen == 0
        drive(self.pos, self.heading, self.motion * active, self.turn * active, *LIMITS)
        rel = self.food[:, None] - self.pos.reshape(self.fields, self.per_field, 1, 2)
        near = np.einsum("fpkc,fpkc->fpk", rel, rel) < (2 * RADIUS) ** 2
        eaten = near & active.reshape(self.fields, self.per_field, 1)
        if eaten.any():
            self.reward += eaten.reshape(self.n, -1) @ VALUE
            taken = eaten.any(axis=1)
            self.food[taken] = uniform_in(self.rng, int(taken.sum()), HALF, 1.0)
        shooting = self.laser & active
        if shooting.any():
            self.frozen[self._lasered(shooting)] = FREEZE
        np.maximum(self.frozen - 1, 0, out=self.frozen)
        interrupted = self.episode_steps >= MAX_STEP
        return interrupted, interrupted

    def _lasered(self, shooting: np.ndarray) -> np.ndarray:
        """Bool (n,): agents in the beam of a shooting agent of their field."""
        pos = self.pos.reshape(self.fields, self.per_field, 2)
        c = np.cos(self.heading).reshape(self.fields, self.per_field, 1)
        s = np.sin(self.heading).reshape(self.fields, self.per_field, 1)
        rel = pos[:, None, :, :] - pos[:, :, None, :]  # [field, shooter, target]
        ahead = c * rel[..., 0] + s * rel[..., 1]
        side = c * rel[..., 1] - s * rel[..., 0]
        beam = (ahead > 0.0) & (ahead < self.beam) & (np.abs(side) < 1.0)
        return (beam & shooting.reshape(self.fields, self.per_field, 1)).any(axis=1).reshape(-1)

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        k, fields = len(rows), self.field[rows]
        x = self.pos[rows, 0, None].astype(np.float32)
        y = self.pos[rows, 1, None].astype(np.float32)
        c = np.cos(self.heading[rows])[:, None].astype(np.float32)
        s = np.sin(self.heading[rows])[:, None].astype(np.float32)
        grid = np.zeros((k, 5, GRID, GRID), dtype=np.float32)
        # walls: cells whose centre (agent + ahead * facing + left * normal) is outside the
        # (square) field
        wx = (x + c * AHEAD)[:, :, None] - (s * LEFT)[:, None, :]
        wy = (y + s * AHEAD)[:, :, None] + (c * LEFT)[:, None, :]
        np.greater(
            np.maximum(np.abs(wx), np.abs(wy)), HALF[0], out=grid[:, WALL_TAG], casting="unsafe"
        )
        # food, poison and the other agents of the field, one tag per cell (the last wins)
        others = self.pos.reshape(self.fields, self.per_field, 2)[fields].copy()
        others[np.arange(k), self.local[rows]] = FAR  # not itself
        points = np.concatenate([self.food[fields], others], axis=1)
        frozen = (self.frozen > 0).reshape(self.fields, self.per_field)[fields]
        tags = np.concatenate(
            [np.broadcast_to(KIND, (k, len(KIND))), np.where(frozen, FROZEN_TAG, AGENT_TAG)],
            axis=1,
        )
        dx, dy = points[..., 0] - x, points[..., 1] - y
        row = np.floor(GRID / 2 - (c * dx + s * dy)).astype(np.int64)
        col = np.floor(GRID / 2 - (c * dy - s * dx)).astype(np.int64)
        seen = (row >= 0) & (row < GRID) & (col >= 0) & (col < GRID)
        cell = (np.arange(k)[:, None] * GRID + row) * GRID + col
        cell, tags = cell[seen][::-1], tags[seen][::-1]
        cell, first = np.unique(cell, return_index=True)
        agent, rest = np.divmod(cell, GRID * GRID)
        row, col = np.divmod(rest, GRID)
        grid[agent, WALL_TAG, row, col] = 0.0  # a cell at the edge shows what is in it
        grid[agent, tags[first], row, col] = 1.0
        return [grid]

    def _mask(self, behavior: int, rows: np.ndarray) -> np.ndarray:
        mask = np.zeros((len(rows), 2), dtype=bool)
        mask[:, 1] = self.frozen[rows] > 0  # no laser while frozen
        return mask


CAMERA = FirstPerson(84, 60.0, eye=0.5, wall_height=1.5)
FOOD_CODE, POISON_CODE, AGENT_CODE, FROZEN_CODE = range(4, 8)  # after the scene's codes
ITEM_CODES = np.where(KIND == FOOD_TAG, FOOD_CODE, POISON_CODE)
# food green, poison red, an agent blue, a frozen agent white
PALETTE_CHANNELS = np.ascontiguousarray(
    palette((40, 210, 40), (210, 40, 40), (40, 40, 210), (240, 240, 240)).T
)


class VisualFoodCollector(GridFoodCollector):
    name = "VisualFoodCollector"
    behaviors = (
        Behavior(
            "VisualFoodCollector?team=0",
            (Sensor.camera("CameraSensor", 3, 84, 84), Sensor.vector("VectorSensor_size1", 1)),
            continuous=3,
            branches=(2,),
        ),
    )
    fields_per_area = 2
    layout = ((0, 0),) * 4

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        k, fields = len(rows), self.field[rows]
        others = self.pos.reshape(self.fields, self.per_field, 2)[fields]
        frozen = (self.frozen > 0).reshape(self.fields, self.per_field)[fields]
        agents = np.where(frozen, FROZEN_CODE, AGENT_CODE)
        agents[np.arange(k), self.local[rows]] = -1  # not itself
        code = np.concatenate(
            [
                np.broadcast_to(ITEM_CODES, (k, len(KIND))),
                agents,
            ],
            axis=1,
        )
        objects = np.concatenate([self.food[fields], others], axis=1)
        radius = np.full(code.shape, RADIUS)
        half = np.full(k, HALF[0])
        image = CAMERA.codes(self.pos[rows], self.heading[rows], half, objects, radius, code)
        frozen_flag = (self.frozen[rows, None] > 0).astype(np.float32)
        return [colours(image, PALETTE_CHANNELS), frozen_flag]
