"""Pyramids: press the switch, then topple the pyramid that appears (ML-Agents example).

Sixteen rooms, one agent each (ids 0..15, no groups), spec-faithful to the dump. A room
(24 x 24) is split into nine spawn areas of 8 x 8, as ``PyramidArea``'s. At every episode
begin they are shuffled, as ``PyramidAgent.OnEpisodeBegin`` does: the agent goes to a
random spot of the first (1 from its edges), the switch to the second, the third is where
the pyramid will rise, and each of the other six gets a stone pyramid. Stone pyramids are
obstacles: they stop the agent and block its rays. Touching the switch turns it on and
raises the gold pyramid in its area; touching that pyramid knocks it over and reaches the
gold: the reward is set to +2 and the episode ends. Every step costs -1 / MaxStep (MaxStep
2500, interrupted), so the return is about 2 - time for a solved room and -1 for an
unsolved one. Random play solves none of 60 episodes; the scripted expert 88 of 100.

Sensors as in the dump: three RayPerceptionSensors of 7 rays with 6 tags (block, wall,
goal, switch off, switch on, stone): ahead over ±70°, behind over ±70°, and a longer,
higher fan over ±45° that sees the gold on top of the pyramid (goal; the rays below see its
bricks, block); and a vector of 4: switch state, then the agent's (commanded) velocity in
its own frame (right, up, forward). Actions: one branch of 5 (none, forward, back, turn
right, turn left); nothing masked.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import DT, FAR, MOVES, ArenaEnv, drive, limits, overlaps, steer
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor
from unitysim.envs.perception import Rays, perceive

HALF = (12.0, 12.0)
CELL = 2.0 * HALF[0] / 3  # the nine spawn areas: 3 x 3 squares of this side
RADIUS = 0.5
SPEED = 3.0
LIMITS = limits(HALF, RADIUS)
MAX_STEP = 2500
BLOCK, WALL, GOAL, SWITCH_OFF, SWITCH_ON, STONE = range(6)
SENSORS = (Rays(3, 70.0, 20.0, 6), Rays(3, 70.0, 20.0, 6, backward=True), Rays(3, 45.0, 30.0, 6))
# ray objects of a room: the switch, the gold pyramid, six stone pyramids
SWITCH, PYRAMID, STONES = 0, 1, slice(2, 8)
SIZES = np.array([[0.4, 0.4]] + [[0.9, 0.9]] * 7)
LOW = np.array([SWITCH_OFF, BLOCK, *[STONE] * 6, WALL])  # ray tags per object, then the edge


class Pyramids(ArenaEnv):
    name = "Pyramids"
    behaviors = (
        Behavior(
            "Pyramids?team=0",
            (
                Sensor.vector("RayPerceptionSensor", SENSORS[0].size),
                Sensor.vector("RayPerceptionSensor1", SENSORS[1].size),
                Sensor.vector("RayPerceptionSensor2", SENSORS[2].size),
                Sensor.vector("VectorSensor_size4", 4),
            ),
            branches=(5,),
        ),
    )
    fields_per_area = 16

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.objects = np.zeros((self.n, len(SIZES), 2))  # centres; the pyramid FAR until raised
        self.switched = np.zeros(self.n, dtype=bool)
        self.pyramid_area = np.zeros(self.n, dtype=np.intp)  # where it rises when switched

    def _begin(self, which: np.ndarray) -> None:
        k = int(which.sum())
        areas = self.rng.permuted(np.tile(np.arange(9), (k, 1)), axis=1)  # a shuffle per room
        spots = self._spot_in(areas.ravel()).reshape(k, 9, 2)
        self.pos[which] = spots[:, 0]
        self.heading[which] = self.rng.uniform(-np.pi, np.pi, k)
        self.motion[which] = 0.0
        self.turn[which] = 0.0
        objects = np.full((k, len(SIZES), 2), FAR)
        objects[:, SWITCH] = spots[:, 1]
        objects[:, STONES] = spots[:, 3:]
        self.objects[which] = objects
        self.pyramid_area[which] = areas[:, 2]
        self.switched[which] = False

    def _spot_in(self, areas: np.ndarray) -> np.ndarray:
        """A random point in each spawn area, 1 from its edge (objects of neighbouring areas
        never overlap, nor an agent and a stone)."""
        corner = np.column_stack([areas % 3, areas // 3]) * CELL - np.asarray(HALF)
        return corner + CELL / 2 + self.rng.uniform(-1.0, 1.0, (len(areas), 2)) * (CELL / 2 - 1)

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        c = MOVES[np.clip(actions.discrete[:, 0], 0, 4)]
        self.motion[rows], self.turn[rows] = steer(c[:, 0], c[:, 1], c[:, 2], SPEED, np.pi)

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        drive(self.pos, self.heading, self.motion, self.turn, *LIMITS)
        self._stop_at_stones()
        self.reward -= 1.0 / MAX_STEP
        touched = overlaps(
            self.pos, RADIUS, self.objects[:, :2] - SIZES[:2], self.objects[:, :2] + SIZES[:2]
        )
        pressed = touched[:, SWITCH] & ~self.switched
        if pressed.any():
            self.switched |= pressed
            self.objects[pressed, PYRAMID] = self._spot_in(self.pyramid_area[pressed])
        done = touched[:, PYRAMID]
        if done.any():
            self.reward[done] = 2.0  # SetReward: the step's reward is replaced
        interrupted = ~done & (self.episode_steps >= MAX_STEP)
        return done | interrupted, interrupted

    def _stop_at_stones(self) -> None:
        """An agent that walked into a stone pyramid is put back out of it along the axis it
        went in least (it slides along the stone's side)."""
        stones = self.objects[:, STONES]
        gap = np.abs(self.pos[:, None, :] - stones) - (SIZES[STONES] + RADIUS)  # (n, 6, 2)
        inside = (gap < 0).all(axis=2)
        if not inside.any():
            return
        rows, which = np.nonzero(inside)
        axis = gap[rows, which].argmax(axis=1)  # the shallower way out
        side = np.sign(self.pos[rows, axis] - stones[rows, which, axis])
        self.pos[rows, axis] -= side * gap[rows, which, axis]

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        centers = self.objects[rows]
        lo, hi = centers - SIZES, centers + SIZES
        pos, heading = self.pos[rows], self.heading[rows]
        low = np.tile(LOW, (len(rows), 1))
        low[:, SWITCH] = np.where(self.switched[rows], SWITCH_ON, SWITCH_OFF)
        high = low.copy()
        high[:, PYRAMID] = GOAL  # the gold on top of the pyramid
        ahead, behind, above = perceive(SENSORS, pos, heading, lo, hi, HALF, (low, low, high))
        velocity = self.motion[rows] / DT  # as commanded, in the agent's frame
        vector = np.column_stack(
            [self.switched[rows], -velocity.imag, np.zeros(len(rows)), velocity.real]
        )
        return [ahead, behind, above, vector]
