"""DungeonEscape: three knights, a dragon, a key and a door (ML-Agents example, spec-faithful).

Twelve rooms with a group of three agents each (ids 0..35, group ids 1..12, as in the
dump). A scripted dragon walks from the middle of the room to its portal on the -x wall;
if it gets there the group's episode ends (done, nothing gained). The agent that touches
the dragon kills it and is sacrificed: its episode ends and it disappears (no more infos)
while the dragon drops the key. An agent that picks up the key and touches the door on the
+x wall frees the group: ``AddGroupReward(1)`` and ``EndGroupEpisode`` for the agents
left. MaxEnvironmentSteps 2500 interrupts the group. When a room resets, a sacrificed
agent comes back as a re-enabled Unity agent does: with a new agent id.

Sensors as in the dump: ``RBSensor`` (10: position / 7 as x, y, z, rotation quaternion,
commanded velocity / speed), 15 rays over ±90° with 6 tags (wall, agent, door, key,
dragon, portal), 3 frames stacked: 360, and whether the agent holds the key (1).
Actions: one branch of 7 (none, forward, back, turn right, turn left, left, right);
nothing masked.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import DT, FAR, MOVES, ArenaEnv, drive, limits, overlaps, steer
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor, StatsMethod
from unitysim.envs.perception import FrameStack, Rays, perceive

HALF = (7.0, 7.0)
RADIUS = 0.5
SPEED = 3.0
DRAGON_SPEED = 0.7
LIMITS = limits(HALF, RADIUS)
MAX_ENV_STEPS = 2500
WALL, AGENT, DOOR, KEY, DRAGON, PORTAL = range(6)
RAYS = Rays(7, 90.0, 20.0, 6)
AGENTS = 3
# ray objects of a room: the three agents, door, key, dragon, portal; then the walls
TAGS = np.array([AGENT, AGENT, AGENT, DOOR, KEY, DRAGON, PORTAL, WALL])
SIZES = np.array([[RADIUS] * 2] * AGENTS + [[0.2, 1.0], [0.3, 0.3], [0.6, 0.6], [0.2, 1.0]])
DOOR_AT = np.array([HALF[0] - 0.2, 0.0])


class DungeonEscape(ArenaEnv):
    name = "DungeonEscape"
    behaviors = (
        Behavior(
            "DungeonEscape?team=0",
            (
                Sensor.vector("RBSensor", 10),
                Sensor.vector("StackingSensor_size3_RayPerceptionSensor", 3 * RAYS.size),
                Sensor.vector("VectorSensor_size1", 1),
            ),
            branches=(7,),
        ),
    )
    fields_per_area = 12
    layout = ((0, 1),) * AGENTS

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.has_key = np.zeros(self.n, dtype=bool)
        self.things = np.zeros((self.fields, 4, 2))  # door, key, dragon, portal (FAR = gone)
        self.rays = FrameStack(self.n, 3, RAYS.size)
        self.field_over = np.zeros(self.fields, dtype=bool)  # set by each physics step
        self._killed = np.zeros(self.n, dtype=bool)
        self._nobody = np.zeros(self.n, dtype=bool)
        self._no_room = np.zeros(self.fields, dtype=bool)

    def _begin(self, which: np.ndarray) -> None:
        """Room reset (the rows of a room always begin together): knights on the west side,
        the dragon in the middle, its portal somewhere on the west wall, no key."""
        fields = np.zeros(self.fields, dtype=bool)
        fields[self.field[which]] = True
        k, f = int(which.sum()), int(fields.sum())
        self.pos[which] = np.column_stack(
            [self.rng.uniform(-6.0, -2.0, k), self.rng.uniform(-6.0, 6.0, k)]
        )
        self.heading[which] = self.rng.uniform(-np.pi, np.pi, k)
        self.motion[which] = 0.0
        self.turn[which] = 0.0
        self.has_key[which] = False
        self.rays.clear(which)
        self.things[fields, 0] = DOOR_AT
        self.things[fields, 1] = FAR
        self.things[fields, 2] = np.column_stack(
            [self.rng.uniform(0.0, 3.0, f), self.rng.uniform(-4.0, 4.0, f)]
        )
        self.things[fields, 3] = np.column_stack(
            [np.full(f, -HALF[0] + 0.2), self.rng.uniform(-5.0, 5.0, f)]
        )
        self.field_steps[fields] = 0

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        c = MOVES[np.clip(actions.discrete[:, 0], 0, 6)]
        self.motion[rows], self.turn[rows] = steer(c[:, 0], c[:, 1], c[:, 2], SPEED, np.pi)

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        drive(self.pos, self.heading, self.motion, self.turn, *LIMITS)
        dragon, portal = self.things[:, 2], self.things[:, 3]  # a dead dragon is FAR away
        way = portal - dragon
        distance = np.sqrt(np.einsum("fk,fk->f", way, way))
        walk = np.minimum(1.0, DRAGON_SPEED * DT / (distance + 1e-9))
        dragon += way * np.where(distance < FAR / 2, walk, 0.0)[:, None]
        escaped = distance < 0.9
        touched = overlaps(self.pos, RADIUS, *self._boxes(self.things[self.field, :3], 3))
        touched &= self.alive[:, None]
        killer = self._nobody
        freed = self._no_room
        if touched.any():
            killer, freed = self._touch(touched)
        timeout = self.field_steps >= MAX_ENV_STEPS
        self.field_over = freed | escaped | timeout
        over = self.field_over[self.field] & self.alive
        self._killed = killer
        return over | killer, over & (timeout & ~freed & ~escaped)[self.field]

    def _touch(self, touched: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Agents touching (door, key, dragon): kills, keys, escapes; returns the killers
        and the rooms whose group got out."""
        killer = self._first(touched[:, 2])
        if killer.any():  # the dragon dies and drops the key; its killer is sacrificed
            fields = self.field[killer]
            self.things[fields, 1] = self.things[fields, 2]
            self.things[fields, 2] = FAR
            self.record_stat("Environment/DragonsKilled", float(killer.sum()), StatsMethod.SUM)
        finder = self._first(touched[:, 1] & ~killer)
        if finder.any():
            self.has_key |= finder
            self.things[self.field[finder], 1] = FAR
        freed = np.zeros(self.fields, dtype=bool)
        freed[self.field[touched[:, 0] & self.has_key & ~killer]] = True
        self.group_reward[freed[self.field] & self.alive & ~killer] += 1.0  # AddGroupReward
        return killer, freed

    def _first(self, hits: np.ndarray) -> np.ndarray:
        """Bool (n,): of the agents in ``hits``, only the first of each room."""
        per_room = hits.reshape(self.fields, AGENTS)
        first = np.zeros_like(per_room)
        rooms = per_room.any(axis=1)
        first[rooms, per_room[rooms].argmax(axis=1)] = True
        return first.reshape(-1)

    @staticmethod
    def _boxes(centers: np.ndarray, first: int) -> tuple[np.ndarray, np.ndarray]:
        """Boxes around ``centers`` (..., k, 2), sized as the ray objects ``first`` on."""
        sizes = SIZES[first : first + centers.shape[1]]
        return centers - sizes, centers + sizes

    def _ended(self, ended: np.ndarray, interrupted: np.ndarray) -> None:
        """The sacrificed disappear; rooms that are over reset, bringing them back as new
        agents (new ids)."""
        self.alive[self._killed] = False
        self.motion[self._killed] = 0.0
        self.turn[self._killed] = 0.0
        rows = self.field_over[self.field]
        self._renew_ids(rows & ~self.alive)
        self.alive[rows] = True
        self._start(rows)

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        fields = self.field[rows]
        agents = np.where(self.alive[:, None], self.pos, FAR).reshape(self.fields, AGENTS, 2)
        centers = np.concatenate([agents[fields], self.things[fields]], axis=1)
        lo, hi = self._boxes(centers, 0)
        pos, heading = self.pos[rows], self.heading[rows]
        table = np.broadcast_to(TAGS, (len(rows), len(TAGS)))
        (frame,) = perceive((RAYS,), pos, heading, lo, hi, HALF, table)
        half_turn = heading / 2.0
        zero = np.zeros(len(rows))
        velocity = np.exp(1j * heading) * self.motion[rows] / (DT * SPEED)  # as commanded
        body = np.column_stack(
            [
                pos[:, 0] / HALF[0],
                zero,
                pos[:, 1] / HALF[1],
                zero,
                np.sin(half_turn),
                zero,
                np.cos(half_turn),
                velocity.real,
                zero,
                velocity.imag,
            ]
        )
        return [body, self.rays.push(rows, frame), self.has_key[rows, None]]
