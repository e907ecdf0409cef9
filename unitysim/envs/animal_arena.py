"""AnimalArena: find the green food in a walled arena from a first-person camera (AnimalAI-like).

Why: the other visual environments look down on grids, but AnimalAI's agents see their arena
through an 84 x 84 camera. This environment lets the pipeline (PNG on the wire, CNN in the
learner) move and learn from images of that kind without a Unity build.

Each area has ``fields_per_area`` = 8 arenas with one agent each (``num_areas`` multiplies
this). Eight agents share one message's fixed costs while a step stays near 1 ms. Ids are
0..n-1 and are kept across episodes. An arena is a walled square. Its food items are green
spheres resting on the floor, placed at random, at least 1 unit clear of the agent (each
item is redrawn up to 10 times; only a tiny arena can fail that). The agent starts at a
random place and heading. Touching food gives +1 and ends the episode. (AnimalAI's GoodGoal
also ends it, but scales the reward by the goal's size; here the reward is always +1.) Every
decision costs -1 / T. After T decisions the episode ends interrupted (max step). An arena
without food (food_count 0) only ends at T.

Observations:

- ``CameraSensor`` (3, 84, 84), RGB, sent as PNG. A column ray caster with a 70 degree field
  of view: sky, walls (two shades, one per axis, so corners show), floor, and green food whose
  height and width shrink with distance. Every colour is k/255, so PNG is lossless.
- ``Velocity`` (3,): the agent's velocity in its own frame (x right, y up = 0, z forward), in
  units/s.

Actions are branches (3, 3), as in AnimalAI: 0 nothing / 1 forward / 2 backward, and
0 nothing / 1 turn right / 2 turn left.

Each decision is 0.1 s: Unity's decision period of 5 physics steps of 0.02 s, folded into
one integration step. The agent turns 10 degrees, its velocity relaxes exactly (linear drag)
towards 8 units/s along the new heading, and then it moves. Walls stop it (the velocity into
the wall drops to 0). Food touched anywhere along the move counts. Because
``decision_period`` is 1, T counts decisions and every message carries decisions, never
terminal rows alone.

Environment parameters (the EnvironmentParameters side channel) are read each time episodes
begin, so a curriculum takes effect at each arena's next episode:

- ``arena_size`` (12): side of the square arena, clipped to [4, 60]. AnimalAI's is 40, but
  a random policy finds the food in about a quarter of 250-step episodes at 12 and a tenth
  at 20, so 12 gives PPO a denser start; a curriculum can grow it;
- ``food_count`` (1): food items per arena, clipped to [0, 8];
- ``food_radius`` (0.75): clipped to [0.2, min(3, arena_size / 8)];
- ``episode_length`` (250): T, decisions per episode, at least 1.

Cost, measured on the 2-core dev machine (best of 7 runs of 100 steps, other jobs
running): ``step`` plus the player's PNG and protobuf encoding takes 0.6 ms for 4 agents,
1.0 ms for 8 and 2.2 ms for 16, about 0.13 ms per agent-step. Rendering and PNG encoding
are each about 45% of that.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import AXIS, FAR, ArenaEnv, uniform_in
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor
from unitysim.envs.perception import FirstPerson, colours, palette

IMAGE = 84
CAMERA = FirstPerson(IMAGE, 70.0, eye=0.5, wall_height=1.5)
FOOD = 4  # after FirstPerson's scene codes (sky, wall x, wall y, floor)
PALETTE = palette((40, 210, 40))  # food is the only green-dominant colour
PALETTE_CHANNELS = np.ascontiguousarray(PALETTE.T)  # (3, codes)

AGENT_RADIUS = 0.5
STEP_SECONDS = 0.1  # one decision: 5 physics steps of 0.02 s
DRAG = 5.0  # 1/s
TOP_SPEED = 8.0  # units/s, the speed at which drag balances full acceleration
DECAY = np.exp(-DRAG * STEP_SECONDS)
TURN = np.radians(10.0)  # per decision
MAX_FOOD = 8
CLEARANCE = 1.0  # free space between the agent and every food item at an episode's start
PLACEMENT_TRIES = 10
FOOD_REWARD = 1.0


class AnimalArena(ArenaEnv):
    name = "AnimalArena"
    behaviors = (
        Behavior(
            "AnimalArena?team=0",
            (Sensor.camera("CameraSensor", 3, IMAGE, IMAGE), Sensor.vector("Velocity", 3)),
            branches=(3, 3),
        ),
    )
    decision_period = 1  # each "physics step" here is a whole decision, see the docstring
    fields_per_area = 8

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.vel = np.zeros((self.n, 2))  # world frame, units/s
        self.push = np.zeros(self.n)  # +1 forward, -1 backward, 0 none
        self.half = np.full(self.n, 6.0)  # half the arena's side
        self.length = np.full(self.n, 250, dtype=np.int64)  # T of the current episode
        self.food = np.full((self.n, MAX_FOOD, 2), FAR)
        self.present = np.zeros((self.n, MAX_FOOD), dtype=bool)
        self.radius = np.full(self.n, 0.75)

    def _begin(self, which: np.ndarray) -> None:
        """A fresh arena per agent, laid out with the parameters as they are now."""
        k = int(which.sum())
        if k == 0:
            return
        half = float(np.clip(self.params.get("arena_size", 12.0), 4.0, 60.0)) / 2
        count = int(np.clip(round(self.params.get("food_count", 1.0)), 0, MAX_FOOD))
        radius = float(np.clip(self.params.get("food_radius", 0.75), 0.2, min(3.0, half / 4)))
        self.half[which] = half
        self.length[which] = max(1, round(self.params.get("episode_length", 250.0)))
        self.radius[which] = radius
        pos = uniform_in(self.rng, k, (half, half), AGENT_RADIUS)
        self.pos[which] = pos
        self.heading[which] = self.rng.uniform(-np.pi, np.pi, k)
        self.vel[which] = 0.0
        self.push[which] = 0.0
        self.turn[which] = 0.0
        self.food[which] = FAR
        self.present[which] = False
        if count == 0:
            return
        food = uniform_in(self.rng, k * count, (half, half), radius).reshape(k, count, 2)
        for _ in range(PLACEMENT_TRIES):  # redraw the items too close to their agent
            gap = radius + AGENT_RADIUS + CLEARANCE
            near = ((food - pos[:, None]) ** 2).sum(axis=2) < gap * gap
            if not near.any():
                break
            food[near] = uniform_in(self.rng, int(near.sum()), (half, half), radius)
        self.food[which, :count] = food
        self.present[which, :count] = True

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        branch = np.clip(actions.discrete, 0, 2)
        self.push[rows] = AXIS[branch[:, 0]]
        self.turn[rows] = -AXIS[branch[:, 1]] * TURN  # 1 = right = clockwise

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        """One decision: turn, accelerate against drag, move, stop at walls, eat."""
        self.heading += self.turn
        ahead = np.column_stack([np.cos(self.heading), np.sin(self.heading)])
        self.vel *= DECAY
        self.vel += ahead * (self.push * (TOP_SPEED * (1.0 - DECAY)))[:, None]
        start = self.pos.copy()
        self.pos += self.vel * STEP_SECONDS
        limit = (self.half - AGENT_RADIUS)[:, None]
        blocked = np.abs(self.pos) > limit
        np.clip(self.pos, -limit, limit, out=self.pos)
        self.vel[blocked] = 0.0
        # closest approach of each food item to the move's segment
        move = self.pos - start
        rel = self.food - start[:, None]
        t = (
            np.einsum("nkd,nd->nk", rel, move)
            / np.maximum(np.einsum("nd,nd->n", move, move), 1e-12)[:, None]
        )
        gap = rel - np.clip(t, 0.0, 1.0)[:, :, None] * move[:, None]
        reach = (self.radius + AGENT_RADIUS)[:, None]
        eaten = (self.present & ((gap * gap).sum(axis=2) < reach * reach)).any(axis=1)
        self.reward -= 1.0 / self.length
        self.reward[eaten] += FOOD_REWARD
        interrupted = ~eaten & (self.episode_steps >= self.length)
        return eaten | interrupted, interrupted

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        heading, vel = self.heading[rows], self.vel[rows]
        cos, sin = np.cos(heading), np.sin(heading)
        velocity = np.zeros((len(rows), 3), dtype=np.float32)
        velocity[:, 0] = vel[:, 0] * sin - vel[:, 1] * cos  # right
        velocity[:, 2] = vel[:, 0] * cos + vel[:, 1] * sin  # forward
        return [self.camera(rows), velocity]

    def camera(self, rows: np.ndarray) -> np.ndarray:
        """First-person images (k, 3, H, W) in [0, 1] of ``rows``."""
        code = np.where(self.present[rows], FOOD, -1)
        radius = np.broadcast_to(self.radius[rows, None], code.shape)
        image = CAMERA.codes(
            self.pos[rows], self.heading[rows], self.half[rows], self.food[rows], radius, code
        )
        return colours(image, PALETTE_CHANNELS)
