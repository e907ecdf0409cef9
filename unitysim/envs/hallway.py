"""Hallway: go to the goal whose colour matches the symbol (ML-Agents example, spec-faithful).

Sixteen hallways, one agent each (ids 0..15, no groups). As in the real scene, the agent
starts facing any way a little way into a 16 x 8 hallway; the symbol, an orange or red
block, stands near the hallway's start (+-2 across), and the two goals, one orange and one
red on random sides, at its far end. Rays reach 8, so the symbol is out of sight over
the last 5 of the 9 to 12 units to the goals: the agent must look for the symbol, then
remember its colour on the way (ML-Agents trains it with memory). It runs at 6 units/s
(0.6 a decision), so random play reaches a goal in about 4% of episodes. Touching the
goal of the symbol's colour sets the reward to +1, the other goal to -0.1; both end the
episode. Every step costs -1 / MaxStep (3000, interrupted).

Sensors as in the dump: 5 rays over +-60 degrees (tags orange goal, red goal, orange
block, red block, wall), 3 frames stacked: 105; and StepCount / MaxStep, 3 frames stacked:
3. Actions: one branch of 5 (none, forward, back, turn right, turn left); nothing masked.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import MOVES, ArenaEnv, drive, limits, overlaps, steer
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor
from unitysim.envs.perception import FrameStack, Rays, perceive

HALF = (8.0, 4.0)
RADIUS = 0.5
LIMITS = limits(HALF, RADIUS)
MAX_STEP = 3000
ORANGE_GOAL, RED_GOAL, ORANGE_BLOCK, RED_BLOCK, WALL = range(5)
RAY_LENGTH = 8.0
RAYS = Rays(2, 60.0, RAY_LENGTH, 5)
# ray objects of a hallway: the symbol (its place across drawn per episode), the goal at
# +y, the goal at -y
CENTERS = np.array([[-6.5, 0.0], [7.5, 2.0], [7.5, -2.0]])
SIZES = np.array([[0.5, 0.5], [0.5, 0.8], [0.5, 0.8]])
GOALS_LO, GOALS_HI = CENTERS[1:] - SIZES[1:], CENTERS[1:] + SIZES[1:]
SYMBOL_ACROSS = 2.0  # the symbol stands within +-2 of the hallway's middle


class Hallway(ArenaEnv):
    name = "Hallway"
    behaviors = (
        Behavior(
            "Hallway?team=0",
            (
                Sensor.vector("StackingSensor_size3_RayPerceptionSensor", 3 * RAYS.size),
                Sensor.vector("StackingSensor_size3_VectorSensor_size1", 3),
            ),
            branches=(5,),
        ),
    )
    fields_per_area = 16

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.red = np.zeros(self.n, dtype=bool)  # the symbol's colour
        self.orange_up = np.zeros(self.n, dtype=bool)  # the orange goal is the one at +y
        self.centers = np.broadcast_to(CENTERS, (self.n, 3, 2)).copy()  # symbol's y drawn
        self.rays = FrameStack(self.n, 3, RAYS.size)
        self.clock = FrameStack(self.n, 3, 1)

    def _begin(self, which: np.ndarray) -> None:
        k = int(which.sum())
        self.pos[which] = np.column_stack(
            [self.rng.uniform(-5.0, -2.0, k), self.rng.uniform(-2.4, 2.4, k)]
        )
        self.heading[which] = self.rng.uniform(-np.pi, np.pi, k)
        self.centers[which, 0, 1] = self.rng.uniform(-SYMBOL_ACROSS, SYMBOL_ACROSS, k)
        self.motion[which] = 0.0
        self.turn[which] = 0.0
        self.red[which] = self.rng.random(k) < 0.5
        self.orange_up[which] = self.rng.random(k) < 0.5
        self.rays.clear(which)
        self.clock.clear(which)

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        c = MOVES[np.clip(actions.discrete[:, 0], 0, 4)]
        self.motion[rows], self.turn[rows] = steer(c[:, 0], c[:, 1], c[:, 2], 6.0, np.pi)

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        drive(self.pos, self.heading, self.motion, self.turn, *LIMITS)
        self.reward -= 1.0 / MAX_STEP
        touched = overlaps(self.pos, RADIUS, GOALS_LO, GOALS_HI)
        done = touched.any(axis=1)
        if done.any():  # SetReward: the step's reward is replaced
            # the touched goal is orange if it is the +y one and orange is up, or vice versa
            orange = np.where(touched[:, 0], self.orange_up, ~self.orange_up)
            self.reward[done] = np.where(orange != self.red, 1.0, -0.1)[done]
        interrupted = ~done & (self.episode_steps >= MAX_STEP)
        return done | interrupted, interrupted

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        up = self.orange_up[rows]
        table = np.empty((len(rows), 4), dtype=np.int64)
        table[:, 0] = np.where(self.red[rows], RED_BLOCK, ORANGE_BLOCK)
        table[:, 1] = np.where(up, ORANGE_GOAL, RED_GOAL)
        table[:, 2] = np.where(up, RED_GOAL, ORANGE_GOAL)
        table[:, 3] = WALL
        lo, hi = self.centers[rows] - SIZES, self.centers[rows] + SIZES
        (frame,) = perceive((RAYS,), self.pos[rows], self.heading[rows], lo, hi, HALF, table)
        time = (self.episode_steps[rows] / MAX_STEP).astype(np.float32)[:, None]
        return [self.rays.push(rows, frame), self.clock.push(rows, time)]
