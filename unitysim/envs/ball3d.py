"""3DBall: twelve platforms each balancing a ball (the ML-Agents example, batched).

Dynamics follow ``Ball3DAgent``: the action tilts the platform by up to 2 degrees per
physics step about z and x (within about ±29 degrees); the ball rolls down the slope;
the agent gets +0.1 per decision while the ball stays on (``SetReward``, so the reward
of a decision period is the last step's) and -1 and the end of its episode when the ball
falls (relative y < -2, or |dx| or |dz| > 3). MaxStep 5000 physics steps, a decision
every 5 steps with the last action repeated in between: a perfect episode earns 100.

Environment parameters, as in the example: ``gravity`` (9.81), ``mass`` (1; a heavier
ball is pushed less by the moving platform) and ``scale`` (1; the ball's size).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from unitysim.envs.base import (
    Actions,
    AgentInfos,
    Behavior,
    Output,
    Parameters,
    Sensor,
    SimEnv,
    StatsMethod,
)

DT = 0.02  # Unity's fixed time step
DECISION_PERIOD = 5
MAX_STEP = 5000
HALF_WIDTH = 2.5  # the platform is 5 x 5
MAX_TILT = np.degrees(2 * np.arcsin(0.25))  # |rotation.z| < 0.25 as a quaternion component
ROLLING = 5.0 / 7.0  # solid sphere rolling without slipping
BALL_RADIUS = 0.5


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
        self.tilt = np.zeros((n, 2), dtype=np.float64)  # degrees about z, about x
        self.pos = np.zeros((n, 3), dtype=np.float64)  # ball relative to the platform
        self.vel = np.zeros((n, 3), dtype=np.float64)
        self.action = np.zeros((n, 2), dtype=np.float64)
        self.reward = np.zeros(n, dtype=np.float32)
        self.episode_steps = np.zeros(n, dtype=np.int64)
        self.academy_steps = 0
        self.gravity = self.mass = self.scale = 1.0

    # --- episode handling ------------------------------------------------------------

    def _begin_episodes(self, which: np.ndarray) -> None:
        """``OnEpisodeBegin``: random small tilt, ball dropped from 4 units above."""
        k = int(which.sum())
        if k == 0:
            return
        self.gravity = self.params.get("gravity", 9.81)
        self.mass = max(self.params.get("mass", 1.0), 1e-3)
        self.scale = max(self.params.get("scale", 1.0), 1e-3)
        self.tilt[which] = self.rng.uniform(-10.0, 10.0, size=(k, 2))
        self.pos[which] = np.column_stack(
            [self.rng.uniform(-1.5, 1.5, k), np.full(k, 4.0), self.rng.uniform(-1.5, 1.5, k)]
        )
        self.vel[which] = 0.0
        self.action[which] = 0.0
        self.reward[which] = 0.0
        self.episode_steps[which] = 0

    def _observe(self) -> np.ndarray:
        half = np.radians(self.tilt) / 2.0
        rotation = np.sin(half)  # quaternion z and x components for small combined tilts
        return np.column_stack([rotation, self.pos, self.vel]).astype(np.float32)

    def _decisions(self) -> AgentInfos:
        infos = AgentInfos.build(self.ids, [self._observe()], reward=self.reward)
        self.reward[:] = 0.0
        return infos

    # --- the contract ----------------------------------------------------------------

    def reset(self) -> Output:
        self.academy_steps = 0
        self._begin_episodes(np.ones(len(self.ids), dtype=bool))
        return {self.behaviors[0].name: self._decisions()}

    def step(self, actions: Mapping[str, Actions]) -> Output:
        behavior = self.behaviors[0].name
        if behavior in actions and len(actions[behavior]):
            # Decisions are always for every agent, in id order.
            self.action[:] = np.clip(actions[behavior].continuous, -1.0, 1.0)
        while True:
            self.academy_steps += 1
            fell, interrupted = self._physics_step()
            done = fell | interrupted
            terminal = None
            if done.any():
                terminal = AgentInfos.build(
                    self.ids[done],
                    [self._observe()[done]],
                    reward=self.reward[done],
                    done=True,
                    max_step_reached=interrupted[done],
                )
                self.record_stat("Ball/Fell", float(fell.sum()), StatsMethod.SUM)
                self._begin_episodes(done)
            if self.academy_steps % DECISION_PERIOD == 0:
                decisions = self._decisions()
                rows = decisions if terminal is None else AgentInfos.concat([terminal, decisions])
                return {behavior: rows}
            if terminal is not None:
                return {behavior: terminal}

    def _physics_step(self) -> tuple[np.ndarray, np.ndarray]:
        """One FixedUpdate: act, move the ball, and judge; returns (fell, interrupted)."""
        turn = 2.0 * self.action  # degrees this step about z, about x
        tilt_z, tilt_x = self.tilt[:, 0], self.tilt[:, 1]
        turn[:, 0] = np.where(
            ((tilt_z < MAX_TILT) & (turn[:, 0] > 0)) | ((tilt_z > -MAX_TILT) & (turn[:, 0] < 0)),
            turn[:, 0],
            0.0,
        )
        turn[:, 1] = np.where(
            ((tilt_x < MAX_TILT) & (turn[:, 1] > 0)) | ((tilt_x > -MAX_TILT) & (turn[:, 1] < 0)),
            turn[:, 1],
            0.0,
        )
        self.tilt += turn

        radius = BALL_RADIUS * self.scale
        sin_z, sin_x = np.sin(np.radians(self.tilt[:, 0])), np.sin(np.radians(self.tilt[:, 1]))
        x, z = self.pos[:, 0], self.pos[:, 2]
        over = (np.abs(x) <= HALF_WIDTH) & (np.abs(z) <= HALF_WIDTH)
        surface = -x * np.tan(np.radians(self.tilt[:, 0])) + z * np.tan(np.radians(self.tilt[:, 1]))
        resting = over & (self.pos[:, 1] <= surface + radius + 1e-6)

        # Free fall for balls in the air (or off the platform).
        self.vel[:, 1] -= self.gravity * DT
        # Rolling along the slope for balls on the platform; a tilting platform also shoves
        # the ball, less so a heavy one.
        shove = np.radians(turn) / DT * radius * 0.05 / self.mass
        ax = -self.gravity * ROLLING * sin_z - shove[:, 0]
        az = self.gravity * ROLLING * sin_x + shove[:, 1]
        self.vel[resting, 0] += ax[resting] * DT
        self.vel[resting, 2] += az[resting] * DT
        self.pos += self.vel * DT
        landed = over & (self.pos[:, 1] < surface + radius)
        self.pos[landed, 1] = (surface + radius)[landed]
        self.vel[landed, 1] = 0.0

        self.episode_steps += 1
        fell = (
            (self.pos[:, 1] < -2.0)
            | (np.abs(self.pos[:, 0]) > 3.0)
            | (np.abs(self.pos[:, 2]) > 3.0)
        )
        interrupted = ~fell & (self.episode_steps >= MAX_STEP)
        self.reward[:] = np.where(fell, -1.0, 0.1)  # SetReward, not AddReward
        return fell, interrupted
