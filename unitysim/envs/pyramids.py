"""Pyramids: press the switch, then topple the pyramid that appears (ML-Agents example).

Sixteen areas, one agent each (ids 0..15, no groups), spec-faithful to the dump and laid
out as ML-Agents' ``AreaPB`` prefab: a 99 x 99 floor split into a 3 x 3 grid of rooms
about 32 wide by interior walls (four cruciform walls and eight side walls) with openings
of about 11 and 18 between rooms; in each room a spawn area of 25 x 25. At every episode
begin the nine spawn areas are shuffled, as ``PyramidAgent.OnEpisodeBegin`` does: the
agent goes to a random spot of the first, the switch to the second, the third is where the
pyramid will rise, and each of the other six gets a stone pyramid. Walls and stone
pyramids stop the agent and block its rays. Touching the switch turns it on and raises the
gold pyramid in its area; touching that pyramid knocks it over and reaches the gold: the
reward is set to +2 and the episode ends. Every step costs -1 / MaxStep (MaxStep 5000,
interrupted), so the return is about 2 - time for a solved area and -1 for an unsolved
one.

Movement as the prefab's rigid body: forward or back adds a velocity change of 2 per
physics step, drag 2 takes it down (about 45 per second at most), a turn is 4 degrees
per step. Simplified: the pyramid is reached by touching it (the real one falls and its
gold brick must then be touched), stones do not topple, the switch does not block.

Sensors as in the dump: three RayPerceptionSensors of 7 rays with 6 tags (block, wall,
goal, switch off, switch on, stone), 35 long: ahead over ±70°, behind over ±70°, and a
higher fan over ±45° that sees the gold on top of the pyramid (goal; the rays below see its
bricks, block); and a vector of 4: switch state, then the agent's velocity in its own
frame (right, up, forward). Actions: one branch of 5 (none, forward, back, turn right,
turn left); nothing masked.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import FAR, RigidBodyEnv, collide, limits, overlaps
from unitysim.envs.base import Behavior, Parameters, Sensor
from unitysim.envs.perception import Rays, perceive

HALF = (49.5, 49.5)
SPAWN = 30.0  # spawn areas' centres: -30, 0, 30 on each axis
SPAWN_REACH = 25.0 / 2.1  # PlaceObject: within scale / 2.1 of the centre
RADIUS = 0.5
LIMITS = limits(HALF, RADIUS)
MAX_STEP = 5000
BLOCK, WALL, GOAL, SWITCH_OFF, SWITCH_ON, STONE = range(6)
RAY = 35.0
SENSORS = (Rays(3, 70.0, RAY, 6), Rays(3, 70.0, RAY, 6, backward=True), Rays(3, 45.0, RAY, 6))
# ray objects of an area: the switch, the gold pyramid, six stone pyramids
SWITCH, PYRAMID, STONES = 0, 1, slice(2, 8)
SIZES = np.array([[2.0, 2.0]] + [[2.25, 2.25]] * 7)


def _walls() -> tuple[np.ndarray, np.ndarray]:
    """The interior walls (lo, hi), 1 thick, on the lines x = ±16.5 and y = ±16.5: on
    each line a side wall from the outer wall to 35 at both ends and a cruciform wall's
    arm over 9..24 on both sides, leaving openings over 24..35 and -9..9."""
    segments = [(35.0, HALF[0]), (9.0, 24.0), (-24.0, -9.0), (-HALF[0], -35.0)]
    boxes = []
    for line in (-16.5, 16.5):
        for a, b in segments:
            boxes.append(((a, line - 0.5), (b, line + 0.5)))  # along x
            boxes.append(((line - 0.5, a), (line + 0.5, b)))  # along y
    lo, hi = (np.array(side) for side in zip(*boxes, strict=True))
    return lo, hi


WALLS_LO, WALLS_HI = _walls()
WALL_CENTRES, WALL_HALVES = (WALLS_LO + WALLS_HI) / 2, (WALLS_HI - WALLS_LO) / 2
LOW = np.array([SWITCH_OFF, BLOCK, *[STONE] * 6, *[WALL] * len(WALLS_LO), WALL])  # then the edge


class Pyramids(RigidBodyEnv):
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
    push_change, drag, turn_rate = 2.0, 2.0, float(np.radians(200.0))

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.objects = np.zeros((self.n, len(SIZES), 2))  # centres; the pyramid FAR until raised
        self.switched = np.zeros(self.n, dtype=bool)
        self.pyramid_area = np.zeros(self.n, dtype=np.intp)  # where it rises when switched

    def _begin(self, which: np.ndarray) -> None:
        k = int(which.sum())
        areas = self.rng.permuted(np.tile(np.arange(9), (k, 1)), axis=1)  # a shuffle per area
        spots = self._spot_in(areas.ravel()).reshape(k, 9, 2)
        self.pos[which] = spots[:, 0]
        self.heading[which] = self.rng.uniform(-np.pi, np.pi, k)
        self._stand(which)
        objects = np.full((k, len(SIZES), 2), FAR)
        objects[:, SWITCH] = spots[:, 1]
        objects[:, STONES] = spots[:, 3:]
        self.objects[which] = objects
        self.pyramid_area[which] = areas[:, 2]
        self.switched[which] = False

    def _spot_in(self, areas: np.ndarray) -> np.ndarray:
        """A random point in each spawn area, as ``PyramidArea.PlaceObject`` picks it."""
        centre = (np.column_stack([areas % 3, areas // 3]) - 1) * SPAWN
        return centre + self.rng.uniform(-SPAWN_REACH, SPAWN_REACH, (len(areas), 2))

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        self._glide()
        walls = np.broadcast_to(WALL_CENTRES, (self.n, *WALL_CENTRES.shape))
        centres = np.concatenate([self.objects[:, STONES], walls], axis=1)
        halves = np.concatenate([SIZES[STONES], WALL_HALVES])
        collide(self.pos, self.velocity, LIMITS, centres, halves, RADIUS)  # walls, stones
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

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        centers = self.objects[rows]
        k = len(rows)
        lo = np.concatenate([centers - SIZES, np.broadcast_to(WALLS_LO, (k, *WALLS_LO.shape))], 1)
        hi = np.concatenate([centers + SIZES, np.broadcast_to(WALLS_HI, (k, *WALLS_HI.shape))], 1)
        pos, heading = self.pos[rows], self.heading[rows]
        low = np.tile(LOW, (k, 1))
        low[:, SWITCH] = np.where(self.switched[rows], SWITCH_ON, SWITCH_OFF)
        high = low.copy()
        high[:, PYRAMID] = GOAL  # the gold on top of the pyramid
        ahead, behind, above = perceive(SENSORS, pos, heading, lo, hi, HALF, (low, low, high))
        cos, sin = np.cos(heading), np.sin(heading)
        vx, vy = self.velocity[rows, 0], self.velocity[rows, 1]
        forward, left = vx * cos + vy * sin, -vx * sin + vy * cos
        vector = np.column_stack([self.switched[rows], -left, np.zeros(k), forward])
        return [ahead, behind, above, vector]
