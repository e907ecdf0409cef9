"""PushBlock and PushBlockCollab: push blocks into the goal (ML-Agents examples).

Both are laid out from release 21's ``PushBlockArea`` and ``PushBlockCollabAreaGrid``
prefabs, ``PushAgentBasic``, ``PushAgentCollab`` and ``PushBlockEnvController``: a 25 x 25
court walled on all sides, the goal a strip 4.15 deep across its -y end, agents cubes of 1
that are rigid bodies of mass 10 and drag 4 pushed by one branch of 7 actions (none,
forward, back, turn right, turn left, strafe left, strafe right; a velocity change of 3 a
physics step ahead, 0.75 of it sideways, turns of 200 degrees a second), deciding every 5
steps and acting between. Blocks, then agents, spawn at random in the middle half of the
court (``GetRandomSpawnPos``), none overlapping one placed before it; PushBlock's spawn
check, a box of 2.5 about the spot, also keeps them 2.5 clear of the goal.

**PushBlock**: 32 areas, one agent and one 2 x 2 block each (ids 0..31, no groups). A block
that touches the goal pays +5 and ends the episode; every physics step costs -1 / MaxStep
(5000, then interrupted). Sensors: two RayPerceptionSensors of 7 rays over ±90°, 12 long,
with 3 tags (block, goal, wall), each stacked 3 frames (105): one at the agent's height,
and one 1.5 higher (the ``Offset`` one, sorted first by name), which sees over the block and
the goal and meets only the walls.

**PushBlockCollab**: 4 areas, 3 agents in one group each (ids 0..11, group ids 1..4) and
six blocks: two of 1 x 1 worth 1, two of 2 x 2 worth 2, two of 3 x 3 worth 3. A block that
touches the goal vanishes and pays its worth to the group; when all six are in, the group's
episode ends (``EndGroupEpisode``). Every physics step costs the group -0.5 /
MaxEnvironmentSteps (5000, then ``GroupEpisodeInterrupted``); agents have no MaxStep. Each
agent sees a GridSensor of 20 x 20 cells of 1 around it, turned with it (row 0 is 10 ahead,
column 0 is 10 to the left), channels wall, agent, goal, small, large and very large block:
a cell shows what it overlaps, one tag per cell (blocks over agents, agents over the goal,
the goal over walls), sent PNG-compressed (two PNGs for six channels) as the prefab's
compression setting says.

Simplified: blocks do not turn; an agent moves a block it runs into by sharing its velocity
along the side it hit (equal masses, as PushBlock's block and agent); the collab's blocks
need as many agents pushing together as ML-Agents' documentation says (1, 2 and 3 by size),
standing in for their masses of 10, 100 and 150 against the ground's friction; the goal is
a strip agents cross; agents pass through each other; ray casts are thin (the prefab's
sphere casts are 0.5 wide).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from unitysim.envs.arena import DT, FAR, MOVES, RigidBodyEnv, limits
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor
from unitysim.envs.perception import FrameStack, Rays, perceive

HALF = (12.5, 12.5)
RADIUS = 0.5
LIMITS = limits(HALF, RADIUS)
GOAL_EDGE = -HALF[1] + 4.15  # the goal strip: y below this
GOAL_LO, GOAL_HI = np.array([-HALF[0], -HALF[1]]), np.array([HALF[0], GOAL_EDGE])
SPAWN = HALF[0] * 0.5  # spawnAreaMarginMultiplier 0.5
STRAFE = 0.75
BLOCK_DRAG = 0.5
MAX_STEP = 5000
BLOCK, GOAL, WALL = range(3)  # PushBlock's ray tags
RAYS = Rays(3, 90.0, 12.0, 3)
FRAMES = 3
# PushBlockCollab's grid
WALL_TAG, AGENT_TAG, GOAL_TAG = range(3)  # then one tag per block size
GRID = 20
CELLS = (GRID / 2 - 0.5 - np.arange(GRID)).astype(np.float32)  # cell centres, agent frame
COLLAB_AGENTS = 3
COLLAB_HALVES = np.array([0.5, 0.5, 1.0, 1.0, 1.5, 1.5])
COLLAB_WORTH = np.array([1.0, 1.0, 2.0, 2.0, 3.0, 3.0])
COLLAB_PUSHERS = np.array([1, 1, 2, 2, 3, 3])  # agents it takes to move it


class _Court(RigidBodyEnv):
    """Agents and blocks on the walled court; subclasses say which blocks and who scores."""

    push_change, drag, turn_rate = 3.0, 4.0, float(np.radians(200.0))
    halves: ClassVar[np.ndarray]  # (B,) half sizes of a field's blocks
    pushers: ClassVar[np.ndarray]  # (B,) agents that must push a block together to move it
    goal_clearance: ClassVar[float] = 0.0  # how far from the goal a spawn point must be

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.per_field = len(self.layout)
        count = len(self.halves)
        self.side = np.zeros(self.n)  # the stored strafe: +1 right, -1 left
        self.blocks = np.full((self.fields, count, 2), FAR)
        self.block_velocity = np.zeros((self.fields, count, 2))
        self.active = np.zeros((self.fields, count), dtype=bool)

    def _spawn(self, fields: np.ndarray) -> None:
        """Blocks then agents of ``fields`` at random spots, each clear of those before."""
        for f in fields:  # a few areas per ended episode, a few objects each
            placed: list[tuple[np.ndarray, float]] = []
            for b, half in enumerate(self.halves):
                self.blocks[f, b] = self._clear_spot(placed, float(half))
                placed.append((self.blocks[f, b], float(half)))
            for row in np.flatnonzero(self.field == f):
                self.pos[row] = self._clear_spot(placed, RADIUS)
                placed.append((self.pos[row], RADIUS))
        self.block_velocity[fields] = 0.0
        self.active[fields] = True

    def _clear_spot(self, placed: list[tuple[np.ndarray, float]], half: float) -> np.ndarray:
        while True:
            spot = self.rng.uniform((-SPAWN, max(-SPAWN, GOAL_EDGE + self.goal_clearance)), SPAWN)
            if all((np.abs(spot - at) >= half + other).any() for at, other in placed):
                return spot

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        c = MOVES[np.clip(actions.discrete[:, 0], 0, len(MOVES) - 1)]
        self.push[rows], self.side[rows] = c[:, 0], c[:, 1] * STRAFE
        self.turn[rows] = c[:, 2] * self.turn_rate * DT

    def _move(self) -> np.ndarray:
        """One physics step of agents and blocks; returns the blocks that touch the goal
        (fields, B)."""
        right = np.column_stack([np.sin(self.heading), -np.cos(self.heading)])
        self.velocity += self.push_change * self.side[:, None] * right
        self._glide()  # turn, push forward, drag, move
        self.block_velocity /= 1.0 + BLOCK_DRAG * DT
        self.blocks += self.block_velocity * DT * self.active[..., None]
        self._contacts()
        edge = (HALF[0] - self.halves)[None, :, None]  # blocks in play stop at the walls
        out = (np.abs(self.blocks) > edge) & self.active[..., None]
        self.block_velocity[out] = 0.0
        self.blocks[out] = (np.sign(self.blocks) * edge)[out]
        self.pos.clip(*LIMITS, out=self.pos)
        self.velocity[(self.pos <= LIMITS[0]) | (self.pos >= LIMITS[1])] = 0.0
        return self.active & (self.blocks[..., 1] - self.halves < GOAL_EDGE)

    def _contacts(self) -> None:
        """Agents inside a block are put back out along the shallower axis. Where enough
        agents push a block that way, it and they share their mean velocity along that
        axis; otherwise the agents lose their velocity into it, as against a wall."""
        pos = self.pos.reshape(self.fields, self.per_field, 2)
        vel = self.velocity.reshape(self.fields, self.per_field, 2)
        rel = pos[:, :, None, :] - self.blocks[:, None, :, :]  # (F, A, B, 2)
        gap = np.abs(rel) - (self.halves[:, None] + RADIUS)
        inside = (gap < 0).all(-1) & self.active[:, None, :]
        if not inside.any():
            return
        f, a, b = np.nonzero(inside)
        axis = gap[f, a, b].argmax(-1)
        side = np.sign(rel[f, a, b, axis])  # the agent's side of the block along ``axis``
        pos[f, a, axis] -= side * gap[f, a, b, axis]
        into = -side * (vel[f, a, axis] - self.block_velocity[f, b, axis]) > 0
        count = np.zeros(self.active.shape, dtype=np.int64)
        np.add.at(count, (f[into], b[into]), 1)
        moves = count[f, b] >= self.pushers[b]
        mean = np.zeros(self.active.shape)
        np.add.at(mean, (f[into], b[into]), vel[f[into], a[into], axis[into]])
        shared = (mean[f, b] + self.block_velocity[f, b, axis]) / (count[f, b] + 1)
        pushing = into & moves
        self.block_velocity[f[pushing], b[pushing], axis[pushing]] = shared[pushing]
        vel[f[into], a[into], axis[into]] = np.where(moves[into], shared[into], 0.0)


class PushBlock(_Court):
    name = "PushBlock"
    behaviors = (
        Behavior(
            "PushBlock?team=0",
            (
                Sensor.vector("StackingSensor_size3_OffsetRayPerceptionSensor", FRAMES * RAYS.size),
                Sensor.vector("StackingSensor_size3_RayPerceptionSensor", FRAMES * RAYS.size),
            ),
            branches=(7,),
        ),
    )
    fields_per_area = 32
    halves = np.array([1.0])  # block_scale 2
    pushers = np.array([1])
    goal_clearance = 2.5

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.low = FrameStack(self.n, FRAMES, RAYS.size)
        self.high = FrameStack(self.n, FRAMES, RAYS.size)
        self.heading[:] = self.rng.uniform(-np.pi, np.pi, self.n)

    def _begin(self, which: np.ndarray) -> None:
        # the agent keeps its heading: OnEpisodeBegin turns the whole area with it
        self._spawn(self.field[which])
        self._stand(which)
        self.side[which] = 0.0
        self.low.clear(which)
        self.high.clear(which)

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        scored = self._move()[:, 0]
        self.reward -= 1.0 / MAX_STEP
        self.reward[scored] += 5.0
        interrupted = ~scored & (self.episode_steps >= MAX_STEP)
        return scored | interrupted, interrupted

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        k, fields = len(rows), self.field[rows]
        block = self.blocks[fields]  # (k, 1, 2)
        lo = np.concatenate([block - self.halves[:, None], np.broadcast_to(GOAL_LO, (k, 1, 2))], 1)
        hi = np.concatenate([block + self.halves[:, None], np.broadcast_to(GOAL_HI, (k, 1, 2))], 1)
        low = np.tile(np.array([BLOCK, GOAL, WALL]), (k, 1))
        high = np.tile(np.array([-1, -1, WALL]), (k, 1))  # over the block and the goal
        pos, heading = self.pos[rows], self.heading[rows]
        ahead, above = perceive((RAYS, RAYS), pos, heading, lo, hi, HALF, (low, high))
        return [self.high.push(rows, above), self.low.push(rows, ahead)]


class PushBlockCollab(_Court):
    name = "PushBlockCollab"
    behaviors = (
        Behavior(
            "PushBlockCollab?team=0",
            (Sensor.visual("GridSensor", 3 + 3, GRID, GRID),),
            branches=(7,),
        ),
    )
    fields_per_area = 4
    layout = ((0, 1),) * COLLAB_AGENTS
    halves = COLLAB_HALVES
    pushers = COLLAB_PUSHERS

    def _begin(self, which: np.ndarray) -> None:
        """A field's agents begin together (``ResetScene``): new places and headings."""
        self._spawn(np.unique(self.field[which]))
        self.heading[which] = self.rng.uniform(-np.pi, np.pi, int(which.sum()))
        self._stand(which)
        self.side[which] = 0.0

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        scored = self._move()
        worth = (scored * COLLAB_WORTH).sum(1)
        self.active &= ~scored
        self.blocks[scored] = FAR
        self.block_velocity[scored] = 0.0
        cleared = ~self.active.any(1)
        interrupted = ~cleared & (self.field_steps >= MAX_STEP)
        over = cleared | interrupted
        self.field_steps[over] = 0
        self.group_reward += (worth - 0.5 / MAX_STEP)[self.field]
        return over[self.field], interrupted[self.field]

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        k, fields = len(rows), self.field[rows]
        c = np.cos(self.heading[rows])[:, None, None]
        s = np.sin(self.heading[rows])[:, None, None]
        ahead, left = CELLS[None, :, None], CELLS[None, None, :]
        x = self.pos[rows, 0, None, None] + c * ahead - s * left  # (k, GRID, GRID)
        y = self.pos[rows, 1, None, None] + s * ahead + c * left
        grid = np.zeros((k, 3 + 3, GRID, GRID), dtype=np.float32)
        # a cell shows what it overlaps (its half is 0.5); later tags show over earlier ones
        reach = HALF[0] - 0.5
        tag = np.where((np.abs(x) > reach) | (np.abs(y) > reach), WALL_TAG, -1)
        tag[y < GOAL_EDGE + 0.5] = GOAL_TAG
        others = self.pos.reshape(self.fields, COLLAB_AGENTS, 2)[fields].copy()
        others[np.arange(k), self.local[rows]] = FAR  # not itself
        for j in range(COLLAB_AGENTS):
            tag[_within(x, y, others[:, j], RADIUS + 0.5)] = AGENT_TAG
        for b, half in enumerate(self.halves):
            tag[_within(x, y, self.blocks[fields, b], float(half) + 0.5)] = 3 + b // 2
        agent, row, col = np.nonzero(tag >= 0)
        grid[agent, tag[agent, row, col], row, col] = 1.0
        return [grid]


def _within(x: np.ndarray, y: np.ndarray, centre: np.ndarray, half: float) -> np.ndarray:
    """(k, GRID, GRID): the cell centres ``x``, ``y`` inside each row's square."""
    return (np.abs(x - centre[:, 0, None, None]) < half) & (
        np.abs(y - centre[:, 1, None, None]) < half
    )
