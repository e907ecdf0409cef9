"""3DBall: twelve platforms each balancing a ball (the ML-Agents example, batched).

Dynamics follow ``Ball3DAgent``: the action tilts the platform by up to 2 degrees per
physics step about z and x (within about ±29 degrees); the ball rolls down the slope;
the agent gets +0.1 per decision while the ball stays on (``SetReward``, so the reward
of a decision period is the last step's) and -1 and the end of its episode when the ball
falls (relative y < -2, or |dx| or |dz| > 3). MaxStep 5000 physics steps, a decision
every 5 steps with the last action repeated in between: a perfect episode earns 100.

Environment parameters, as in the example: ``gravity`` (9.81), ``mass`` (1; a heavier
ball is pushed less by the moving platform) and ``scale`` (1; the ball's size).

The stand-in must never be what limits a trainer's throughput, so one physics step is one
call into C (``_ball3d.c``, built by setup.py where a C compiler is) or, without it, a few
dozen in-place numpy operations with the same results (``_move``; to the last bit where
numpy's sin and cos are libm's), on a single (8, n) float64 state array whose rows are
laid out for the maths rather than for the observation: the tilts are stored in radians
and signed so that both horizontal axes obey the same equations (``sigma = [-tilt_z,
tilt_x]``: the slope then pushes ``x`` by ``sin(sigma[0])`` and ``z`` by ``sin(sigma[1])``,
and the surface height is ``x * tan(sigma[0]) + z * tan(sigma[1])``). Episode lengths are
counted from each agent's start step, so MaxStep costs a comparison with one scalar per
step. The tilt limit is Unity's rule unchanged: a turn is applied while the platform is
still inside the limit in the direction of the turn (so it may overshoot by one turn).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import replace
from types import ModuleType
from typing import ClassVar

import numpy as np

from unitysim.envs.base import (
    Actions,
    AgentInfos,
    Behavior,
    Output,
    Parameters,
    Sensor,
    SimEnv,
)
from unitysim.envs.perception import FrameStack

DT = 0.02  # Unity's fixed time step
DECISION_PERIOD = 5
MAX_STEP = 5000
HALF_WIDTH = 2.5  # the platform is 5 x 5
MAX_TILT = np.degrees(2 * np.arcsin(0.25))  # |rotation.z| < 0.25 as a quaternion component
ROLLING = 5.0 / 7.0  # solid sphere rolling without slipping
BALL_RADIUS = 0.5
MAX_SIGMA = float(np.radians(MAX_TILT))
TURN = float(np.radians(2.0))  # radians per physics step at full action
SHOVE = 0.05  # how much of the platform's surface speed a (unit mass) ball picks up
RESTING_TOLERANCE = 1e-6
HARD_STACK = 9  # 3DBallHard: decisions stacked (the example's prefab)

# Rows of the state array: signed tilts (radians), position (x, z, y), velocity (x, z, y).
SIGMA, POS, VEL = slice(0, 2), slice(2, 5), slice(5, 8)
X_Z, Y, V_X_Z, V_Y = slice(2, 4), 4, slice(5, 7), 7
# State rows in observation order: rotation z, x; position x, y, z; velocity x, y, z.
OBS_ROWS = np.array([0, 1, 2, 4, 3, 5, 7, 6])
# From signed tilts (and per-axis turns) back to Unity's (about z, about x) order and signs.
AXIS_SIGN = np.array([[-1.0], [1.0]])
TURN_PER_AXIS = tuple(float(rate) for rate in TURN * AXIS_SIGN[:, 0])  # the C act's rates


def compiled_physics() -> ModuleType | None:
    """The C physics (``_ball3d.c``) where it was built and not switched off with
    ``UNITYSIM_PHYSICS=numpy``; None means the numpy methods below."""
    if os.environ.get("UNITYSIM_PHYSICS", "").lower() == "numpy":
        return None
    try:
        from unitysim.envs import _ball3d  # an optional build product (setup.py)
    except ImportError:
        return None
    return _ball3d


class Ball3D(SimEnv):
    name = "3DBall"
    behaviors = (
        Behavior("3DBall?team=0", (Sensor.vector("VectorSensor_size8", 8),), continuous=2),
    )
    agents_per_area = 12

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        n = self.agents_per_area * self.num_areas
        self.ids = np.arange(n, dtype=np.int32)
        self.state = np.zeros((8, n), dtype=np.float64)  # never rebound: views below
        self.sigma = self.state[SIGMA]
        self.xz = self.state[X_Z]
        self.y = self.state[Y]
        self.pos, self.vel = self.state[POS], self.state[VEL]
        self.v_xz, self.v_y = self.state[V_X_Z], self.state[V_Y]
        self.reach = np.zeros(n, dtype=np.float64)  # max(|x|, |z|): over the platform?
        self.accel = np.zeros((3, n), dtype=np.float64)  # velocity change per step, as vel
        self.turn = np.zeros((2, n), dtype=np.float64)  # signed radians per step, as sigma
        self.direction = np.zeros((2, n), dtype=np.float64)  # sign(turn)
        self.reward = np.zeros(n, dtype=np.float32)
        self.fell = np.zeros(n, dtype=bool)  # written by the compiled step
        self.kernel = compiled_physics()
        logging.getLogger("unitysim").info("3DBall physics: %s", "C" if self.kernel else "numpy")
        self.start = np.zeros(n, dtype=np.int64)  # academy step at which the episode began
        self.academy_steps = 0
        self.next_interrupt = MAX_STEP  # first academy step at which some agent hits MaxStep
        self.gravity = self.mass = self.scale = 1.0
        self._constants()

    def _constants(self) -> None:
        """Per-step coefficients of the current parameters (they change at episode begins)."""
        self.radius = BALL_RADIUS * self.scale
        self.fall_dv = self.gravity * DT
        self.accel[2] = -self.fall_dv  # free fall for every ball, every step
        self.slope_dv = self.gravity * ROLLING * DT
        # The platform's surface speed is turn / DT * radius; a ball picks up SHOVE / mass of
        # it per step: dv = SHOVE * turn * radius / mass.
        self.shove_dv = SHOVE * self.radius / self.mass

    # --- episode handling ------------------------------------------------------------

    def _begin_episodes(self, which: np.ndarray) -> None:
        """``OnEpisodeBegin``: random small tilt, ball dropped from 4 units above."""
        agents = np.flatnonzero(which)  # indices: cheaper than the mask in what follows
        k = len(agents)
        if k == 0:
            return
        self.gravity = self.params.get("gravity", 9.81)
        self.mass = max(self.params.get("mass", 1.0), 1e-3)
        self.scale = max(self.params.get("scale", 1.0), 1e-3)
        self._constants()
        tilt = self.rng.uniform(-10.0, 10.0, size=(k, 2))  # degrees about z, about x
        x, z = self.rng.uniform(-1.5, 1.5, k), self.rng.uniform(-1.5, 1.5, k)
        fresh = np.zeros((8, k))
        fresh[SIGMA] = np.radians(tilt.T) * AXIS_SIGN
        fresh[X_Z] = x, z
        fresh[Y] = 4.0
        self.state[:, agents] = fresh
        self.reach[agents] = np.maximum(np.abs(x), np.abs(z))
        self.turn[:, agents] = 0.0
        self.direction[:, agents] = 0.0
        self.reward[agents] = 0.0
        self.start[agents] = self.academy_steps
        self.next_interrupt = int(self.start.min()) + MAX_STEP

    def _observe(self) -> np.ndarray:
        if self.kernel is not None:
            obs = np.empty((len(self.ids), 8), dtype=np.float32)
            self.kernel.observe(self.state, obs)
            return obs
        rows = self.state[OBS_ROWS]
        rows[:2] = np.sin(rows[:2] * 0.5) * AXIS_SIGN  # quaternion z and x components
        return np.ascontiguousarray(rows.T, dtype=np.float32)

    def _decisions(self) -> AgentInfos:
        infos = AgentInfos.build(self.ids, [self._observe()], reward=self.reward)  # copies
        self.reward.fill(0.0)
        return infos

    def _act(self, continuous: np.ndarray) -> None:
        """Decisions are always for every agent, in id order; NaN means no turn."""
        if self.kernel is not None:  # the C step needs no directions: it takes the signs
            self.kernel.act(continuous, self.turn, *TURN_PER_AXIS)
            return
        action = np.minimum(continuous, 1.0)  # (np.clip's Python wrapper costs more)
        np.maximum(action, -1.0, out=action)
        if np.count_nonzero(np.isnan(action)):
            action = np.nan_to_num(action, nan=0.0)
        np.multiply(action.T, TURN * AXIS_SIGN, out=self.turn)
        np.sign(self.turn, out=self.direction)

    # --- the contract ----------------------------------------------------------------

    def reset(self) -> Output:
        self.academy_steps = 0
        self._begin_episodes(np.ones(len(self.ids), dtype=bool))
        return {self.behaviors[0].name: self._decisions()}

    def step(self, actions: Mapping[str, Actions]) -> Output:
        behavior = self.behaviors[0].name
        if behavior in actions and len(actions[behavior]):
            self._act(actions[behavior].continuous)
        while True:
            self.academy_steps += 1
            fell, interrupted = self._physics_step()
            terminal = None
            if fell is not None or interrupted is not None:
                done = interrupted if fell is None else fell
                done = done if interrupted is None else done | interrupted
                terminal = AgentInfos.build(
                    self.ids[done],
                    [self._observe()[done]],
                    reward=self.reward[done],
                    done=True,
                    max_step_reached=False if interrupted is None else interrupted[done],
                )
                self._begin_episodes(done)
            if self.academy_steps % DECISION_PERIOD == 0:
                decisions = self._decisions()
                rows = decisions if terminal is None else AgentInfos.concat([terminal, decisions])
                return {behavior: rows}
            if terminal is not None:
                return {behavior: terminal}

    def _physics_step(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """One FixedUpdate: act, move the ball, and judge; returns (fell, interrupted), each
        None where no agent fell / no agent can have reached MaxStep (the common case)."""
        fell = self._move() if self.kernel is None else self._move_compiled()
        interrupted = None
        if self.academy_steps >= self.next_interrupt:
            interrupted = self.academy_steps - self.start >= MAX_STEP
            if fell is not None:
                interrupted &= ~fell
            interrupted = interrupted if np.count_nonzero(interrupted) else None
        return fell, interrupted

    def _move_compiled(self) -> np.ndarray | None:
        """``_move`` in C: the same equations in the same order, one loop over the agents."""
        fallen = self.kernel.physics_step(  # type: ignore[union-attr]
            self.state, self.turn, self.reach, self.reward, self.fell,
            self.radius, self.fall_dv, self.slope_dv, self.shove_dv,
            DT, MAX_SIGMA, HALF_WIDTH, RESTING_TOLERANCE,
        )  # fmt: skip
        return self.fell if fallen else None

    def _move(self) -> np.ndarray | None:
        """Tilt, move and judge every agent; returns which balls fell, None if none did."""
        # Turn while inside the limit in the direction of the turn (Unity's rule).
        turn = self.turn * (self.direction * self.sigma < MAX_SIGMA)
        self.sigma += turn
        sin = np.sin(self.sigma)
        tan = sin / np.cos(self.sigma)  # as the C step computes it (np.tan may round apart)

        xz, y = self.xz, self.y
        slope = xz * tan
        top = slope[0] + slope[1]  # the platform's surface under the ball ...
        top += self.radius  # ... where the ball's centre rests
        over = self.reach <= HALF_WIDTH  # as the previous step left the ball
        resting = over & (y - top <= RESTING_TOLERANCE)

        # Free fall for every ball; rolling along the slope for balls on the platform, where a
        # tilting platform also shoves the ball, less so a heavy one.
        roll = sin * self.slope_dv
        roll += turn * self.shove_dv
        np.multiply(roll, resting, out=self.accel[:2])
        self.vel += self.accel
        self.pos += self.vel * DT
        landed = over & (y < top)
        np.copyto(y, top, where=landed)
        np.copyto(self.v_y, 0.0, where=landed)

        reach = np.abs(xz)
        np.maximum(reach[0], reach[1], out=self.reach)
        fell = (self.reach > 3.0) | (y < -2.0)
        self.reward.fill(0.1)  # SetReward, not AddReward; -1 below for balls that fell
        if not np.count_nonzero(fell):
            return None
        self.reward[fell] = -1.0
        return fell


class StackedBall3D(Ball3D):
    """3DBall observed through one StackingSensor over ``_frame()`` (the behavior's only
    sensor): the last ``frames`` frames, oldest first, zeros after an episode begins. The
    current frame is last but not yet kept: terminal rows show it too, and only a decision
    moves the stack on."""

    frames: ClassVar[int]

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.shape = self.behaviors[0].sensors[0].shape
        frame_size = int(np.prod(self.shape)) // self.frames
        self.stack = FrameStack(len(self.ids), self.frames, frame_size)

    def _frame(self) -> np.ndarray:
        """Every agent's current frame, (n, *one frame's shape)."""
        raise NotImplementedError

    def _begin_episodes(self, which: np.ndarray) -> None:
        super()._begin_episodes(which)
        self.stack.clear(which)

    def _observe(self) -> np.ndarray:
        n = len(self.ids)
        now = self._frame().reshape(n, -1)
        flat = np.concatenate([self.stack.buffer[:, self.stack.size :], now], axis=1)
        return flat.reshape(n, *self.shape)

    def _decisions(self) -> AgentInfos:
        frames = self._observe()
        self.stack.buffer[:] = frames.reshape(len(self.ids), -1)
        infos = AgentInfos.build(self.ids, [frames], reward=self.reward)
        self.reward.fill(0.0)
        return infos


class Ball3DHard(StackedBall3D):
    """3DBallHard: the same platforms and physics, observed as the example's
    ``Ball3DHardAgent`` observes them: no velocity (rotation z, x and the ball's position
    relative to the platform, 5 values), stacked over the last 9 decisions by a
    StackingSensor, so a policy must infer the ball's motion from the stack."""

    name = "3DBallHard"
    behaviors = (
        Behavior(
            "3DBallHard?team=0",
            (Sensor.vector(f"StackingSensor_size{HARD_STACK}_VectorSensor_size5", 5 * HARD_STACK),),
            continuous=2,
        ),
    )
    frames = HARD_STACK

    def _frame(self) -> np.ndarray:
        return Ball3D._observe(self)[:, :5]


# Visual3DBall's camera, from the example's prefab: 7 above and 8 behind the platform's
# centre, pitched 30 degrees down, a vertical field of view of 60 degrees, 84 x 84 RGB on
# black, its frames stacked over 4 decisions by a StackingSensor and sent as PNGs
VISUAL_SIZE, VISUAL_STACK = 84, 4
CAMERA = np.array([0.0, 7.0, -8.0])  # x, y, z
_PITCH = np.radians(30.0)
_SPAN = np.tan(np.radians(30.0)) * ((np.arange(VISUAL_SIZE) + 0.5) / VISUAL_SIZE * 2 - 1)
# each pixel's ray (x, y, z), rows from the top of the image
RAYS = (
    np.array([0.0, -np.sin(_PITCH), np.cos(_PITCH)])[None, None, :]
    + _SPAN[None, :, None] * np.array([1.0, 0.0, 0.0])
    - _SPAN[:, None, None] * np.array([0.0, np.cos(_PITCH), np.sin(_PITCH)])
)
RAY_LENGTH2 = (RAYS**2).sum(-1).reshape(1, -1)  # each ray's squared length, [1, P]
PLATFORM_RGB = np.array([0.29, 0.55, 0.87])  # lit from above: darker as it tilts
BALL_RGB = np.array([0.93, 0.62, 0.27])


def render(
    sigma: np.ndarray, x: np.ndarray, z: np.ndarray, y: np.ndarray, radius: float
) -> np.ndarray:
    """(n, 3, 84, 84) in [0, 1]: each platform's top face and its ball, ray-traced from
    the camera (nearest surface wins; the platform's thickness is not drawn)."""
    n = len(x)
    d = RAYS.reshape(1, -1, 3)  # [1, P, 3]
    a, b = np.tan(sigma[0])[:, None], np.tan(sigma[1])[:, None]  # surface y = a x + b z
    # the plane y - a x - b z = 0 along camera + t d
    facing = d[..., 1] - a * d[..., 0] - b * d[..., 2]
    t_plane = -(CAMERA[1] - a * CAMERA[0] - b * CAMERA[2]) / np.where(facing == 0, 1e-9, facing)
    hit_x = CAMERA[0] + t_plane * d[..., 0]
    hit_z = CAMERA[2] + t_plane * d[..., 2]
    on_platform = (t_plane > 0) & (np.abs(hit_x) <= HALF_WIDTH) & (np.abs(hit_z) <= HALF_WIDTH)
    centre = np.stack([x, y, z], axis=1)[:, None, :] - CAMERA  # [n, 1, 3]
    along = (d * centre).sum(-1)  # [n, P]
    gap = (centre**2).sum(-1) - along**2 / RAY_LENGTH2
    inside = radius**2 - gap
    t_ball = (along - np.sqrt(np.maximum(inside, 0.0) * RAY_LENGTH2)) / RAY_LENGTH2
    on_ball = (inside > 0) & (t_ball > 0) & (~on_platform | (t_ball < t_plane))
    light = 1.0 / np.sqrt(1.0 + a**2 + b**2)  # the face's normal against straight down
    image = np.zeros((n, d.shape[1], 3))
    image += (on_platform & ~on_ball)[..., None] * (light[..., None] * PLATFORM_RGB)
    image += on_ball[..., None] * BALL_RGB
    image = image.reshape(n, VISUAL_SIZE, VISUAL_SIZE, 3).transpose(0, 3, 1, 2)
    return image.astype(np.float32)


class Visual3DBall(StackedBall3D):
    """Visual3DBall: 3DBall's platforms and physics seen only through the example's camera
    (``useVecObs`` off): eight platforms, each image the last four decisions' frames, sent
    as four PNGs with the StackingSensor's channel mapping. The colours are the stand-in's."""

    name = "Visual3DBall"
    behaviors = (
        Behavior(
            "Visual3DBall?team=0",
            (
                replace(
                    Sensor.camera(
                        f"StackingSensor_size{VISUAL_STACK}_CameraSensor",
                        3 * VISUAL_STACK,
                        VISUAL_SIZE,
                        VISUAL_SIZE,
                    ),
                    stacks=VISUAL_STACK,
                ),
            ),
            continuous=2,
        ),
    )
    agents_per_area = 8
    frames = VISUAL_STACK

    def _frame(self) -> np.ndarray:
        return render(self.sigma, self.xz[0], self.xz[1], self.y, self.radius)
