"""Pyramids: press the switch, then topple the pyramid that appears (ML-Agents example).

Sixteen rooms, one agent each (ids 0..15, no groups), spec-faithful to the dump. A room
(16 x 16) holds the agent, a switch and three blocks at random places. Touching the
switch turns it on and raises a pyramid with gold on top at a random spot at least 4 away;
touching the pyramid knocks it over and reaches the gold: the reward is set to +2 and the
episode ends. Every step costs -1 / MaxStep (MaxStep 2500, interrupted), so the return is
about 2 - time for a solved room and -1 for an unsolved one. Objects do not block movement.

Sensors as in the dump: three RayPerceptionSensors of 7 rays with 6 tags (block, wall,
goal, switch off, switch on, stone): ahead over ±70°, behind over ±70°, and a longer,
higher fan over ±45° that sees over the stones to the gold (the pyramid reads as goal
there, as stone below); and a vector of 4: switch state, then the agent's (commanded)
velocity in its own frame (right, up, forward). Actions: one branch of 5 (none, forward, back, turn
right, turn left); nothing masked.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import DT, FAR, MOVES, ArenaEnv, drive, limits, overlaps, steer, uniform_in
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor
from unitysim.envs.perception import Rays, perceive

HALF = (8.0, 8.0)
RADIUS = 0.5
SPEED = 3.0
LIMITS = limits(HALF, RADIUS)
MAX_STEP = 2500
BLOCK, WALL, GOAL, SWITCH_OFF, SWITCH_ON, STONE = range(6)
SENSORS = (Rays(3, 70.0, 20.0, 6), Rays(3, 70.0, 20.0, 6, backward=True), Rays(3, 45.0, 30.0, 6))
# ray objects of a room: the switch, the pyramid, three blocks
SIZES = np.array([[0.4, 0.4], [0.9, 0.9], [0.6, 0.6], [0.6, 0.6], [0.6, 0.6]])


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

    def _begin(self, which: np.ndarray) -> None:
        k = int(which.sum())
        self.pos[which] = uniform_in(self.rng, k, HALF, 1.0)
        self.heading[which] = self.rng.uniform(-np.pi, np.pi, k)
        self.motion[which] = 0.0
        self.turn[which] = 0.0
        self.objects[which] = uniform_in(self.rng, k * len(SIZES), HALF, 1.0).reshape(k, -1, 2)
        self.objects[which, 1] = FAR
        self.switched[which] = False

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        c = MOVES[np.clip(actions.discrete[:, 0], 0, 4)]
        self.motion[rows], self.turn[rows] = steer(c[:, 0], c[:, 1], c[:, 2], SPEED, np.pi)

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        drive(self.pos, self.heading, self.motion, self.turn, *LIMITS)
        self.reward -= 1.0 / MAX_STEP
        touched = overlaps(
            self.pos, RADIUS, self.objects[:, :2] - SIZES[:2], self.objects[:, :2] + SIZES[:2]
        )
        pressed = touched[:, 0] & ~self.switched
        if pressed.any():
            self._raise_pyramids(pressed)
        done = touched[:, 1]
        if done.any():
            self.reward[done] = 2.0  # SetReward: the step's reward is replaced
        interrupted = ~done & (self.episode_steps >= MAX_STEP)
        return done | interrupted, interrupted

    def _raise_pyramids(self, pressed: np.ndarray) -> None:
        """The switch turns on; a pyramid appears at least 4 away from the agent."""
        self.switched |= pressed
        k = int(pressed.sum())
        spot = uniform_in(self.rng, k, HALF, 1.5)
        near = np.linalg.norm(spot - self.pos[pressed], axis=1) < 4.0
        spot[near] = -np.sign(self.pos[pressed][near]) * (np.asarray(HALF) - 2.0)  # far corner
        self.objects[pressed, 1] = spot

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        centers = self.objects[rows]
        lo, hi = centers - SIZES, centers + SIZES
        pos, heading = self.pos[rows], self.heading[rows]
        low = np.tile(np.array([0, STONE, BLOCK, BLOCK, BLOCK, WALL]), (len(rows), 1))
        low[:, 0] = np.where(self.switched[rows], SWITCH_ON, SWITCH_OFF)
        high = low.copy()
        high[:, 1] = GOAL  # the gold on top of the pyramid
        ahead, behind, above = perceive(SENSORS, pos, heading, lo, hi, HALF, (low, low, high))
        velocity = self.motion[rows] / DT  # as commanded, in the agent's frame
        vector = np.column_stack(
            [self.switched[rows], -velocity.imag, np.zeros(len(rows)), velocity.real]
        )
        return [ahead, behind, above, vector]
