"""Sorter: touch the numbered tiles around a round arena in increasing order (ML-Agents example).

Laid out as ML-Agents' ``Sorter`` scene and ``SorterAgent``: eight areas, one agent each
(behavior ``Sorter``). Twenty tiles, numbered 1 to 20, stand on a circle of radius 20.5 in
twenty slots 18 degrees apart. At every episode begin the agent is back at the centre,
facing -z (rotated 180 degrees), and ``1 + uniform(num_tiles)`` tiles (``num_tiles``: the
environment parameter, 20 by default, the curriculum's lessons 2, 4, ..., 20) are drawn without
replacement, each put in a slot of its own. Touching the lowest unvisited tile gives +1 and
marks it visited; touching another unvisited tile gives -1 and ends the episode; a visited
one does nothing. The episode also ends when every tile is visited, or at MaxStep 5000
(interrupted). Every physics step costs -1 / 5000. Decisions every 5 steps, the action
repeated between them.

Sensors, sorted by name as Unity sorts them:

- ``BufferSensor``, variable length ``(20, 23)``: one row per spawned tile in increasing
  number, the rest zeros: a one-hot of the tile's number at index ``number`` (1..20), then
  the tile's position minus the agent's in x and z, over 20 (written at indices 20 and 21,
  over tile 20's one-hot, as the example does), then 1 if visited;
- ``RBSensor`` (10): the rigid-body sensor of the agent's own body in its own frame: position
  (0, 0, 0), rotation (0, 0, 0, 1), then its velocity (right, up, forward);
- ``StackingSensor_size2_VectorSensor_size4`` (8): two frames, the older first, of the
  agent's position in the area over 20 (x, z) and its facing (x, z); zeros after a reset.

Actions: three branches of 3: forward / back; right / left (replacing the first branch's
direction when not 0); turn. Movement as the prefab's rigid body: a velocity change of 2
along the chosen direction every physics step, drag 4 (about 23 a second at most), 200
degrees a second of turn. Simplified: the agent is a disc of radius 0.5 kept inside a circle
of radius 19.5 (the tiles' faces), and touches a tile when within 2.2 of its centre.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import DT, RigidBodyEnv
from unitysim.envs.base import NONE_DIM, Actions, Behavior, Parameters, Sensor

TILES = 20
ROW = TILES + 3  # one-hot (index 0 unused), then dx, dz over tile 20's slot, visited
SLOT_ANGLE = 2 * np.pi / TILES
TILE_RADIUS = 20.5  # the tiles' cubes on their circle
AGENT_REACH = 19.5  # how far from the centre the agent's centre goes
TOUCH = 2.2  # agent centre to tile centre, touching
SCALE = 20.0  # positions over 20 in the observations
MAX_STEP = 5000
VARIABLE_SIZE = 4  # DimensionProperty flag on the wire
# branch value -> (forward, right) direction in the agent's frame
AHEAD = np.array([0.0, 1.0, -1.0])


class Sorter(RigidBodyEnv):
    name = "Sorter"
    behaviors = (
        Behavior(
            "Sorter?team=0",
            (
                Sensor("BufferSensor", (TILES, ROW), (VARIABLE_SIZE, NONE_DIM)),
                Sensor.vector("RBSensor", 10),
                Sensor.vector("StackingSensor_size2_VectorSensor_size4", 8),
            ),
            branches=(3, 3, 3),
        ),
    )
    fields_per_area = 8
    push_change, drag, turn_rate = 2.0, 4.0, float(np.radians(200.0))

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.slot = np.full((self.n, TILES), -1, dtype=np.int64)  # per tile number - 1: slot
        self.visited = np.zeros((self.n, TILES), dtype=bool)
        self.strafe = np.zeros(self.n)  # +1 right, -1 left, 0: the forward branch moves
        self.previous = np.zeros((self.n, 4), dtype=np.float32)  # the stacked older frame

    # --- rules ---------------------------------------------------------------------------

    def _begin(self, which: np.ndarray) -> None:
        k = int(which.sum())
        most = int(np.clip(self.params.get("num_tiles", float(TILES)), 1, TILES))
        count = self.rng.integers(1, most + 1, k)
        slots = np.full((k, TILES), -1, dtype=np.int64)
        for row in range(k):  # a few tiles per ended episode: a loop costs nothing here
            numbers = self.rng.choice(TILES, count[row], replace=False)
            slots[row, numbers] = self.rng.choice(TILES, count[row], replace=False)
        self.slot[which] = slots
        self.visited[which] = False
        self.pos[which] = 0.0
        self.heading[which] = -np.pi / 2  # facing -z
        self._stand(which)
        self.strafe[which] = 0.0
        self.previous[which] = 0.0

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        d = np.clip(actions.discrete, 0, 2)
        self.push[rows] = AHEAD[d[:, 0]]
        self.strafe[rows] = AHEAD[d[:, 1]]
        # 1: about -up, 2: about +up (Unity's +up turns +z towards +x: heading decreases)
        self.turn[rows] = AHEAD[d[:, 2]] * self.turn_rate * DT

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        self.heading += self.turn
        facing = np.column_stack([np.cos(self.heading), np.sin(self.heading)])
        right = np.column_stack([np.sin(self.heading), -np.cos(self.heading)])
        strafing = self.strafe != 0
        direction = np.where(
            strafing[:, None], self.strafe[:, None] * right, self.push[:, None] * facing
        )
        self.velocity += self.push_change * direction
        self.velocity /= 1.0 + self.drag * DT
        self.pos += self.velocity * DT
        radius = np.hypot(self.pos[:, 0], self.pos[:, 1])
        out = radius > AGENT_REACH
        if out.any():  # the tiles' faces stop it, its velocity outwards is lost
            normal = self.pos[out] / radius[out, None]
            self.pos[out] = normal * AGENT_REACH
            outward = (self.velocity[out] * normal).sum(1, keepdims=True)
            self.velocity[out] -= np.maximum(outward, 0.0) * normal
        self.reward -= 1.0 / MAX_STEP
        touched = self._touching() & ~self.visited  # (n, TILES)
        done = np.zeros(self.n, dtype=bool)
        if touched.any():
            unvisited = (self.slot >= 0) & ~self.visited
            expected = np.where(unvisited.any(1), unvisited.argmax(1), -1)  # lowest number
            hit = touched.any(1)
            right_tile = hit & touched[np.arange(self.n), np.maximum(expected, 0)]
            wrong = hit & ~right_tile
            self.visited[right_tile, expected[right_tile]] = True
            self.reward[right_tile] += 1.0
            self.reward[wrong] -= 1.0
            finished = right_tile & ~((self.slot >= 0) & ~self.visited).any(1)
            done = wrong | finished
        interrupted = ~done & (self.episode_steps >= MAX_STEP)
        return done | interrupted, interrupted

    def _touching(self) -> np.ndarray:
        """(n, TILES): the agent is at a spawned tile."""
        centres = self._tile_positions()
        gap = np.hypot(*(centres - self.pos[:, None, :]).transpose(2, 0, 1))
        return (self.slot >= 0) & (gap < TOUCH)

    def _tile_positions(self) -> np.ndarray:
        """(n, TILES, 2): each tile's centre (x, z); unspawned ones anywhere."""
        angle = np.maximum(self.slot, 0) * SLOT_ANGLE
        return TILE_RADIUS * np.stack([np.sin(angle), np.cos(angle)], axis=-1)

    # --- sensors -------------------------------------------------------------------------

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        k = len(rows)
        spawned = self.slot[rows] >= 0
        relative = (self._tile_positions()[rows] - self.pos[rows, None, :]) / SCALE
        tiles = np.zeros((k, TILES, ROW), dtype=np.float32)
        tiles[:, :, 1 : TILES + 1] = np.eye(TILES, dtype=np.float32)  # tile j is number j + 1
        tiles[:, :, TILES : TILES + 2] = relative
        tiles[:, :, TILES + 2] = self.visited[rows]
        buffer = np.zeros_like(tiles)
        order = np.argsort(~spawned, axis=1, kind="stable")  # spawned first, by number
        present = np.take_along_axis(spawned, order, 1)
        buffer[present] = np.take_along_axis(tiles, order[:, :, None], 1)[present]
        heading = self.heading[rows]
        cos, sin = np.cos(heading), np.sin(heading)
        vx, vz = self.velocity[rows, 0], self.velocity[rows, 1]
        body = np.zeros((k, 10), dtype=np.float32)
        body[:, 6] = 1.0  # the identity rotation (x, y, z, w)
        body[:, 7], body[:, 9] = vx * sin - vz * cos, vx * cos + vz * sin  # right, forward
        frame = np.column_stack([self.pos[rows] / SCALE, cos, sin]).astype(np.float32)
        stacked = np.concatenate([self.previous[rows], frame], axis=1)
        self.previous[rows] = frame
        return [buffer, body, stacked]
