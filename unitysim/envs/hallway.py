"""Hallway: go to the goal whose colour matches the symbol (ML-Agents example, spec-faithful).

Sixteen hallways, one agent each (ids 0..15, no groups), laid out as ML-Agents'
``SymbolFinderArea`` prefab and ``HallwayAgent.OnEpisodeBegin`` (x here is the prefab's z,
along the hallway; y its x, across): a 49.5 x 19 hallway; the agent starts at x in
[-20, -10], y in [-3, 3], facing any way; the symbol, a 4-wide block, stands across the
hallway's middle at x in [-5, 5] (the orange "O" at y in [-3, 3], the red "X" at y = 0,
as the script places them), and the two 4 x 4 goal pads, one orange and one red on
random sides (y = +-7), lie at the far end (x = 22.29). So the agent passes the symbol on
its way down the hallway and has it behind it for the last 15 to 25 units to the goals,
longer than the rays reach and the 3 stacked frames remember: it needs memory (ML-Agents
trains it with an LSTM). Touching the goal of the symbol's colour sets the reward to +1,
the other goal to -0.1; both end the episode. Every physics step costs -1 / MaxStep
(3000, interrupted); a decision is every 6 steps, acted on at each (500 decisions).

Movement as the prefab's rigid body: forward or back adds a velocity change of 1.5 per
step (``agentRunSpeed``), drag 2 slows it (about 37 per second at most, 4.5 a decision),
a turn is 150 degrees per second (18 a decision); the walls and the symbol stop it.
Simplified: no friction, no gravity (the agent starts on the floor).

Sensors as in the dump: a RayPerceptionSensor of 5 rays over +-70 degrees, 12 long, a
sphere cast of radius 0.5 (tags orange goal, red goal, orange block, red block, wall), 3
frames stacked: 105; and StepCount / MaxStep, 3 frames stacked: 3. Actions: one branch
of 5 (none, forward, back, turn right, turn left); nothing masked.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import RigidBodyEnv, collide, limits, overlaps
from unitysim.envs.base import Behavior, Parameters, Sensor
from unitysim.envs.perception import FrameStack, Rays, perceive

HALF = (24.75, 9.5)
RADIUS = 0.5  # the agent is a unit cube
LIMITS = limits(HALF, RADIUS)
MAX_STEP = 3000
ORANGE_GOAL, RED_GOAL, ORANGE_BLOCK, RED_BLOCK, WALL = range(5)
RAY_LENGTH, CAST_RADIUS = 12.0, 0.5
RAYS = Rays(2, 70.0, RAY_LENGTH, 5)
# the objects of a hallway: the symbol (placed per episode), the goal at +y, the one at -y
SYMBOL, GOALS = 0, slice(1, 3)
SIZES = np.array([[0.5, 2.0], [2.0, 2.0], [2.0, 2.0]])  # half sizes
GOAL_CENTRES = np.array([[22.29, 7.0], [22.29, -7.0]])
GOALS_LO, GOALS_HI = GOAL_CENTRES - SIZES[GOALS], GOAL_CENTRES + SIZES[GOALS]
# a sphere cast: the ray's centre line against everything grown by its radius
SEEN_SIZES = SIZES + CAST_RADIUS
SEEN_HALF = (HALF[0] - CAST_RADIUS, HALF[1] - CAST_RADIUS)


class Hallway(RigidBodyEnv):
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
    push_change, drag, turn_rate = 1.5, 2.0, float(np.radians(150.0))
    decision_period = 6

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.red = np.zeros(self.n, dtype=bool)  # the symbol's colour
        self.orange_up = np.zeros(self.n, dtype=bool)  # the orange goal is the one at +y
        self.centres = np.zeros((self.n, len(SIZES), 2))
        self.centres[:, GOALS] = GOAL_CENTRES
        self.rays = FrameStack(self.n, 3, RAYS.size)
        self.clock = FrameStack(self.n, 3, 1)

    def _begin(self, which: np.ndarray) -> None:
        k = int(which.sum())
        self.red[which] = red = self.rng.random(k) < 0.5
        across = np.where(red, 0.0, self.rng.uniform(-3.0, 3.0, k))
        self.centres[which, SYMBOL] = np.column_stack([self.rng.uniform(-5.0, 5.0, k), across])
        self.pos[which] = np.column_stack(
            [self.rng.uniform(-20.0, -10.0, k), self.rng.uniform(-3.0, 3.0, k)]
        )
        self.heading[which] = self.rng.uniform(-np.pi, np.pi, k)
        self._stand(which)
        self.orange_up[which] = self.rng.random(k) < 0.5
        self.rays.clear(which)
        self.clock.clear(which)

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        self._glide()
        symbol = self.centres[:, SYMBOL : SYMBOL + 1]
        collide(self.pos, self.velocity, LIMITS, symbol, SIZES[SYMBOL:1], RADIUS)
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
        table = np.empty((len(rows), len(SIZES) + 1), dtype=np.int64)
        table[:, SYMBOL] = np.where(self.red[rows], RED_BLOCK, ORANGE_BLOCK)
        table[:, 1] = np.where(up, ORANGE_GOAL, RED_GOAL)
        table[:, 2] = np.where(up, RED_GOAL, ORANGE_GOAL)
        table[:, 3] = WALL
        lo, hi = self.centres[rows] - SEEN_SIZES, self.centres[rows] + SEEN_SIZES
        pos, heading = self.pos[rows], self.heading[rows]
        (frame,) = perceive((RAYS,), pos, heading, lo, hi, SEEN_HALF, table)
        time = (self.episode_steps[rows] / MAX_STEP).astype(np.float32)[:, None]
        return [self.rays.push(rows, frame), self.clock.push(rows, time)]
