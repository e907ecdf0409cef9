"""WallJump: get over the wall to the goal, with a block if the wall is high (spec-faithful).

Twenty-four platforms, one agent each. At every episode begin a platform draws its wall
as ``WallJumpAgent`` does (``Random.Range(0, 5)``): 0 no wall (``no_wall_height``, 0), 1 a
small wall the agent can jump (``small_wall_height``, 4), 2-4 a big wall
(``big_wall_height``, 8) that needs the block pushed against it as a step. Each height is
read from the environment parameters at each episode begin, one draw per agent when it is
a sampler, as the example's ``ConfigureAgent`` reads them (``WallJump_curriculum.yaml``
moves them through its lessons). The
agent then runs under ``SmallWallJump`` (no wall or small wall) or ``BigWallJump``. A
switch shows in the messages as in the real build: the episode's terminal info under the
old behavior, the next decision under the new one. All agents start under SmallWallJump
and the first reset switches every one of them (24 terminal infos there, done and
interrupted, then 12 + 12 decisions with the dump's ids); a later RESET reports the
agents whose behavior changes the same way.

Rules: -0.0005 per step; reaching the goal pad on the far side while on the ground sets
the reward to +1, walking off the platform's long sides sets it to -1; both end the
episode. MaxStep 2000 (interrupted). Heights are in Unity units and scaled by 1/4 here:
the agent jumps 1.5, the block is 1 high, so the small wall (1) can be jumped and the big
one (2) only from the block.

Sensors as in the dump (6 frames stacked): two fans of 7 rays over ±90° with 3 tags
(wall, goal, block), one at knee height (sees the block, any wall taller than it) and one
above the head (only a wall taller than the agent can jump); and the agent's position
on the platform / 20 (x, height, y) with its grounded flag. Actions: forward/back, turn,
right/left, jump; jumping is masked while in the air.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import AXIS, DT, FAR, ArenaEnv, drive, limits, steer
from unitysim.envs.base import Actions, Behavior, Output, Parameters, Sensor
from unitysim.envs.perception import FrameStack, Rays, perceive

HALF = (9.0, 4.0)  # the platform; its long (y) sides are open
RAY_FIELD = (9.6, 50.0)  # rays leave over the open sides unseen
RADIUS = 0.5
LIMITS = limits((HALF[0], FAR), RADIUS)  # nothing holds an agent on the long sides
SPEED = 3.0
# the parameters of the wall configurations 0, 1 and 2-4, with the example's defaults
WALL_HEIGHTS = (("no_wall_height", 0.0), ("small_wall_height", 4.0), ("big_wall_height", 8.0))
GRAVITY = 9.81 * 2.5  # the example's gravity multiplier
JUMP = np.sqrt(2.0 * GRAVITY * 1.5)
BLOCK_TOP = 1.0
MAX_STEP = 2000
SMALL, BIG = 0, 1
WALL, GOAL, BLOCK = range(3)
SENSORS = (Rays(3, 90.0, 20.0, 3), Rays(3, 90.0, 20.0, 3))  # knee height, above the head
# ray objects: the wall, the block, the goal pad, the two end walls; then nothing
SIZES = np.array([[0.5, HALF[1]], [0.5, 0.5], [1.0, 1.0], [0.3, HALF[1]], [0.3, HALF[1]]])
TAGS = np.array([WALL, BLOCK, GOAL, WALL, WALL, -1])
# the dump's first split: which of the 24 platforms get a big wall at the first reset
FIRST_BIG = np.isin(np.arange(24), [2, 3, 6, 8, 9, 10, 14, 16, 18, 19, 21, 23])


def _behavior(name: str) -> Behavior:
    return Behavior(
        f"{name}?team=0",
        (
            Sensor.vector("StackingSensor_size6_OffsetRayPerceptionSensor", 6 * SENSORS[1].size),
            Sensor.vector("StackingSensor_size6_RayPerceptionSensor", 6 * SENSORS[0].size),
            Sensor.vector("StackingSensor_size6_VectorSensor_size4", 24),
        ),
        branches=(3, 3, 3, 2),
    )


class WallJump(ArenaEnv):
    name = "WallJump"
    behaviors = (_behavior("SmallWallJump"), _behavior("BigWallJump"))
    fields_per_area = 24

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        n = self.n
        self.z = np.zeros(n)  # height of the agent's feet
        self.vz = np.zeros(n)
        self.jump = np.zeros(n, dtype=bool)
        self.objects = np.zeros((n, len(SIZES), 2))  # centres of the ray objects
        self.wall = np.zeros(n)  # wall height, 0 = no wall
        self.grounded = np.ones(n, dtype=bool)
        self.first_reset = True
        self.stacks = [FrameStack(n, 6, s.size) for s in SENSORS] + [FrameStack(n, 6, 4)]
        self.knee = np.zeros((n, SENSORS[0].size), dtype=np.float32)  # the latest ray frames
        self.head = np.zeros((n, SENSORS[1].size), dtype=np.float32)

    # --- episodes ---------------------------------------------------------------------

    def _begin(self, which: np.ndarray) -> None:
        k = int(which.sum())
        if self.first_reset:
            big = FIRST_BIG[self.field[which] % 24]
            config = np.where(big, 2, self.rng.integers(0, 2, k))
        else:
            config = self.rng.integers(0, 5, k)
        heights = [  # one draw per agent (a sampler draws anew on each read)
            np.array([self.params.get(key, default) for _ in range(k)]) / 4.0
            for key, default in WALL_HEIGHTS
        ]
        self.wall[which] = np.choose(np.minimum(config, 2), heights)
        self.beh[which] = np.where(config >= 2, BIG, SMALL)
        self.pos[which] = np.column_stack(
            [self.rng.uniform(-8.0, -5.0, k), self.rng.uniform(-3.0, 3.0, k)]
        )
        self.heading[which] = self.rng.uniform(-1.0, 1.0, k)
        self.z[which] = 0.0
        self.vz[which] = 0.0
        self.grounded[which] = True
        self.motion[which] = 0.0
        self.turn[which] = 0.0
        self.jump[which] = False
        objects = np.zeros((k, len(SIZES), 2))
        objects[:, 1] = np.column_stack(
            [self.rng.uniform(-6.0, -2.0, k), self.rng.uniform(-2.5, 2.5, k)]
        )
        objects[:, 2] = np.column_stack([np.full(k, 7.5), self.rng.uniform(-2.5, 2.5, k)])
        objects[:, 3, 0], objects[:, 4, 0] = -RAY_FIELD[0] + 0.3, RAY_FIELD[0] - 0.3
        self.objects[which] = objects
        for stack in self.stacks:
            stack.clear(which)

    def reset(self) -> Output:
        """As the base, plus a terminal info (done, interrupted) under the old behavior for
        every agent whose behavior the new episode changes (at the first reset: all)."""
        before = self.beh.copy()
        first = self.first_reset
        self._restart_all()
        self.first_reset = False
        moved = np.ones(self.n, dtype=bool) if first else self.beh != before
        terminal = None
        if moved.any():
            after = self.beh.copy()
            self.beh[:] = before
            terminal = self._infos(moved, done=True, interrupted=True)
            self.beh[:] = after
            for stack in self.stacks:
                stack.clear(moved)
        return self._output(terminal, self._infos(self.alive))

    # --- physics ----------------------------------------------------------------------

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        d = np.clip(actions.discrete, 0, 2)  # forward/back, turn left/right, right/left, jump
        c = AXIS[d[:, :3]]
        self.motion[rows], self.turn[rows] = steer(c[:, 0], c[:, 2], c[:, 1], SPEED, np.pi)
        self.jump[rows] = d[:, 3] == 1

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        before = self.pos[:, 0].copy()
        drive(self.pos, self.heading, self.motion, self.turn, *LIMITS)
        x, y, z = self.pos[:, 0], self.pos[:, 1], self.z
        # the wall stops an agent lower than its top, on the side it came from
        blocked = (np.abs(x) < 0.5 + RADIUS) & (z < self.wall - 0.05)
        if blocked.any():
            x[blocked] = np.where(before[blocked] < 0, -1.0, 1.0) * (0.5 + RADIUS)
        self._push_block()
        # what the agent can stand on: the floor, the block's top, the wall's top
        block = self.objects[:, 1]
        on_block = (np.abs(x - block[:, 0]) < 0.75) & (np.abs(y - block[:, 1]) < 0.75)
        on_wall = np.abs(x) < 0.5 + RADIUS
        ground = np.maximum(
            np.where(on_block & (z >= BLOCK_TOP - 0.1), BLOCK_TOP, 0.0),
            np.where(on_wall & (z >= self.wall - 0.1), self.wall, 0.0),
        )
        self.vz = np.where(self.jump & (z <= ground), JUMP, self.vz - GRAVITY * DT)
        z += self.vz * DT
        self.grounded = z <= ground
        np.maximum(z, ground, out=z)
        self.vz *= ~self.grounded
        self.reward -= 0.0005
        goal = self.objects[:, 2]
        scored = self.grounded & (np.abs(x - goal[:, 0]) < 1.0) & (np.abs(y - goal[:, 1]) < 1.0)
        fell = np.abs(y) > HALF[1]
        done = scored | fell
        if done.any():  # SetReward: the step's reward is replaced
            self.reward[done] = np.where(scored, 1.0, -1.0)[done]
        interrupted = ~done & (self.episode_steps >= MAX_STEP)
        return done | interrupted, interrupted

    def _push_block(self) -> None:
        """An agent below the block's top pushes it along the axis it comes in on; the block
        stays on the platform and on the near side of any wall, else the agent stops."""
        block = self.objects[:, 1]
        rel = block - self.pos
        reach = 0.5 + RADIUS
        touching = (np.abs(rel) < reach).all(axis=1) & (self.z < BLOCK_TOP - 0.1)
        if not touching.any():
            return
        rows = np.flatnonzero(touching)
        axis = (np.abs(rel[rows, 1]) > np.abs(rel[rows, 0])).astype(np.intp)
        side = np.where(rel[rows, axis] >= 0, 1.0, -1.0)
        wanted = self.pos[rows, axis] + side * reach
        bound = np.where(axis == 0, HALF[0] - 0.5, HALF[1] - 0.5)
        top = np.where((axis == 0) & (self.wall[rows] > 0), -1.0, bound)  # the wall's face
        placed = np.clip(wanted, -bound, top)
        block[rows, axis] = placed
        self.pos[rows, axis] = placed - side * reach

    # --- observations -----------------------------------------------------------------

    def _perceive(self, rows: np.ndarray) -> None:
        """Both fans for the agents of both behaviors: the same sensors on every agent."""
        pos, heading, z = self.pos[rows], self.heading[rows], self.z[rows]
        table = np.broadcast_to(TAGS, (len(rows), len(TAGS)))
        for eye, sensor, frames in ((0.5, SENSORS[0], self.knee), (1.5, SENSORS[1], self.head)):
            visible = np.ones((len(rows), len(SIZES), 1), dtype=bool)
            visible[:, 0, 0] = self.wall[rows] > z + eye
            visible[:, 1, 0] = z + eye < BLOCK_TOP
            seen = np.where(visible, self.objects[rows], FAR)
            (frames[rows],) = perceive(
                (sensor,), pos, heading, seen - SIZES, seen + SIZES, RAY_FIELD, table
            )

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        body = np.column_stack(
            [self.pos[rows, 0], self.z[rows], self.pos[rows, 1], 20.0 * self.grounded[rows]]
        )
        knee, head, vector = self.stacks
        return [
            head.push(rows, self.head[rows]),
            knee.push(rows, self.knee[rows]),
            vector.push(rows, body / 20.0),
        ]

    def _mask(self, behavior: int, rows: np.ndarray) -> np.ndarray:
        mask = np.zeros((len(rows), 11), dtype=bool)
        mask[:, 10] = ~self.grounded[rows]  # no jumping in the air
        return mask
