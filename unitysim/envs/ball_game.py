"""Ball games on an arena field: the rules SoccerTwos and StrikersVsGoalie share.

Why a module of its own: both are teams on a pitch with one ball that is kicked by touch
and scores between the posts. :class:`BallGame` holds those rules once, on top of the
Academy loop of :mod:`unitysim.envs.arena`; ``soccer.py`` and ``strikers.py`` give only
their layout, start positions, goals, sensors and existential rewards.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from unitysim.envs.arena import AXIS, DT, FAR, ArenaEnv, drive, limits, steer
from unitysim.envs.base import Actions, Parameters, StatsMethod
from unitysim.envs.perception import FrameStack, Rays, perceive


class BallGame(ArenaEnv):
    """Teams on a pitch with one ball; a field's episode ends for all on a goal or timeout.

    Agents move by three branches of 3 (forward/back, right/left, turn left/right), as
    ``AgentSoccer``; touching the ball kicks it away (harder when moving forward). The ball
    rolls with friction (``gravity``), bounces off the sides and scores when it crosses a
    goal line between the posts. Team 0 attacks +x. Subclasses give the layout, start
    positions, goals, sensors and existential rewards. Ray objects per field: the ball, the
    goals at -x and +x, then the field's agents in layout order; ``tags`` maps them (and
    last, the side walls) to the tag each observer sees.
    """

    half: ClassVar[tuple[float, float]] = (8.0, 5.0)
    goal_half_width: ClassVar[float] = 1.5
    goals: ClassVar[tuple[bool, bool]] = (True, True)  # is there a goal at -x, at +x
    max_env_steps: ClassVar[int] = 5000  # MaxEnvironmentSteps of the field's controller
    agent_radius: ClassVar[float] = 0.5
    cast_radius: ClassVar[float] = 0.0  # the rays' sphere cast (0: thin rays)
    ball_per_scale: ClassVar[float] = 0.05  # the ball's radius per unit of ``ball_scale``
    start_spread: ClassVar[tuple[float, float]] = (0.5, 0.5)  # uniform +- about ``start``
    heading_spread: ClassVar[float] = 0.3  # radians, uniform +-
    ball_spread: ClassVar[float] = 1.0  # the ball starts uniform within +- this of the centre
    speed: ClassVar[float] = 5.0
    turn_speed: ClassVar[float] = 3.0
    team_of: ClassVar[tuple[int, ...]]  # team per behavior
    existential: ClassVar[tuple[float, ...]]  # per behavior, times 1 / max_env_steps a step
    start: ClassVar[tuple[tuple[float, float, float], ...]]  # per layout agent: x, y, heading
    tags: ClassVar[np.ndarray]  # (agents per field, objects + 1): tag seen by each observer
    rays: ClassVar[tuple[tuple[Rays, ...], ...]]  # ray sensors per behavior, 3 frames each

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.team = np.asarray(self.team_of)[self.beh]
        self._existential = np.asarray(self.existential)[self.beh] / self.max_env_steps
        self.low, self.high = limits(self.half, self.agent_radius)
        self.ball = np.zeros((self.fields, 2))
        self.ball_vel = np.zeros((self.fields, 2))
        self.ball_radius = 0.375
        self.friction = 3.4
        self.ball_touch = 0.0
        self.ball_limit = np.asarray(self.half) - self.ball_radius
        self._no_goal = np.zeros(self.fields, dtype=np.int64)
        self.stacks = [[FrameStack(self.n, 3, r.size) for r in rays] for rays in self.rays]
        self.frames = {
            rays: [np.zeros((self.n, r.size), dtype=np.float32) for r in rays] for rays in self.rays
        }
        # each distinct set of sensors, with which behaviors use it
        self._sensor_sets = [
            (rays, np.array([r == rays for r in self.rays])) for rays in dict.fromkeys(self.rays)
        ]
        # goals: thin boxes on the goal lines between the posts (far away where absent)
        x = self.half[0] - 0.15
        self.goal_centers = np.array([[-x, 0.0], [x, 0.0]])
        self.goal_centers[~np.asarray(self.goals)] = FAR
        # half sizes of the ray objects: ball, two goals, the field's agents
        self.half_sizes = np.full((3 + len(self.layout), 2), self.agent_radius)
        self.half_sizes[1:3] = (0.15, self.goal_half_width)
        # where a sphere cast's centre meets a side
        self._cast_half = (self.half[0] - self.cast_radius, self.half[1] - self.cast_radius)

    def _begin(self, which: np.ndarray) -> None:
        """Field reset (``ResetScene``): every agent of the field to its start, ball near
        the centre; the rows of a field always end their episodes together."""
        fields = np.zeros(self.fields, dtype=bool)
        fields[self.field[which]] = True
        rows = fields[self.field]
        k, f = int(rows.sum()), int(fields.sum())
        self.ball_radius = self.ball_per_scale * self.params.get("ball_scale", 7.5)
        self.friction = 0.35 * self.params.get("gravity", 9.81)
        self.ball_touch = self.params.get("ball_touch", 0.0)
        self.ball_limit = np.asarray(self.half) - self.ball_radius
        start = np.asarray(self.start)[self.local[rows]]
        spread = np.asarray(self.start_spread)
        self.pos[rows] = start[:, :2] + self.rng.uniform(-spread, spread, size=(k, 2))
        h = self.heading_spread
        self.heading[rows] = start[:, 2] + self.rng.uniform(-h, h, size=k)
        self._still(rows)
        b = self.ball_spread
        self.ball[fields] = self.rng.uniform(-b, b, size=(f, 2))
        self.ball_vel[fields] = 0.0
        self.field_steps[fields] = 0
        self.episode_steps[rows] = 0
        for stacks in self.stacks:
            for stack in stacks:
                stack.clear(rows)

    def _still(self, rows: np.ndarray) -> None:
        """At a field's reset: its agents at rest, no command stored."""
        self.motion[rows] = 0.0
        self.turn[rows] = 0.0

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        c = AXIS[np.clip(actions.discrete, 0, 2)]  # forward, right, turn left
        self.motion[rows], self.turn[rows] = steer(
            c[:, 0], c[:, 1], c[:, 2], self.speed, self.turn_speed
        )

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        self._move()
        scored = self._roll_ball()
        self._rewards(scored)
        ended = (scored != 0) | (self.field_steps >= self.max_env_steps)
        return ended[self.field], (ended & (scored == 0))[self.field]

    def _move(self) -> None:
        """The agents' part of one physics step."""
        drive(self.pos, self.heading, self.motion, self.turn, self.low, self.high)

    def _roll_ball(self) -> np.ndarray:
        """Kicks, rolling and bounces of one step; returns +1 / -1 per field for a goal
        at +x / -x, else 0."""
        self._kick()
        self._roll()
        return self._ends()

    def _kick(self) -> None:
        """Touching the ball sends it away from the agent, harder when moving forward."""
        _, kicked, row, away = self._touches()
        if len(kicked) == 0:
            return
        power = np.where(self.motion[row].real > 0, 8.0, 2.0)  # moving forward: a kick
        self.ball_vel[kicked] = away * power[:, None]
        self.reward[row] += 0.2 * self.ball_touch

    def _touches(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Which agents overlap their pitch's ball (fields, agents of a field); the pitches
        where one does, the row of the first, and the unit vector from it to the ball,
        which is put back out to where the two touch."""
        per_field = len(self.layout)
        pos = self.pos.reshape(self.fields, per_field, 2)
        rel = self.ball[:, None, :] - pos
        dist2 = np.einsum("fpk,fpk->fp", rel, rel)
        reach = self.agent_radius + self.ball_radius
        touch = dist2 < reach * reach
        kicked = np.flatnonzero(touch.any(axis=1))
        kicker = touch[kicked].argmax(axis=1)
        away = rel[kicked, kicker] / np.sqrt(np.maximum(dist2[kicked, kicker], 1e-12))[:, None]
        self.ball[kicked] = pos[kicked, kicker] + away * reach
        return touch, kicked, kicked * per_field + kicker, away

    def _roll(self) -> None:
        """The ball rolls on, slowed by a constant friction."""
        speed = np.sqrt(np.einsum("fk,fk->f", self.ball_vel, self.ball_vel))
        self.ball_vel *= np.maximum(0.0, 1.0 - self.friction * DT / (speed + 1e-9))[:, None]
        self.ball += self.ball_vel * DT

    def _ends(self) -> np.ndarray:
        """Goals, and bounces off the sides and the ends outside the goals."""
        out = np.abs(self.ball) > self.ball_limit
        if not out.any():
            return self._no_goal
        # at an end: into the goal between the posts, else bounce like at the sides
        x = self.ball[:, 0]
        mouth = np.abs(self.ball[:, 1]) < self.goal_half_width - self.ball_radius
        into = mouth & np.where(x > 0, self.goals[1], self.goals[0])
        scored = (into & (np.abs(x) > self.half[0])) * np.sign(x).astype(np.int64)
        out[:, 0] &= ~into
        sign = np.sign(self.ball)
        self.ball[out] = (sign * self.ball_limit)[out]
        self.ball_vel[out] = (-0.8 * sign * np.abs(self.ball_vel))[out]
        return scored

    def _rewards(self, scored: np.ndarray) -> None:
        """On a goal, ``AddGroupReward``: 1 minus the time penalty (the field's steps over
        MaxEnvironmentSteps) to the scoring team, -1 to the other; every step, each agent's
        existential reward (``existential`` per behavior, in units of 1 / MaxEnvSteps)."""
        self.reward += self._existential
        if not scored.any():
            return
        rows = (scored != 0)[self.field]
        winner = np.where(scored > 0, 0, 1)[self.field][rows]
        bonus = (1.0 - self.field_steps / self.max_env_steps)[self.field][rows]
        self.group_reward[rows] += np.where(self.team[rows] == winner, bonus, -1.0)
        self.record_stat("Environment/Goals", float((scored != 0).sum()), StatsMethod.SUM)

    def _perceive(self, rows: np.ndarray) -> None:
        """One cast per distinct set of ray sensors (SoccerTwos: one for both teams)."""
        per_field = len(self.layout)
        self.half_sizes[0] = self.ball_radius
        for sensors, uses in self._sensor_sets:
            sel = rows[uses[self.beh[rows]]]
            if len(sel) == 0:
                continue
            fields = self.field[sel]
            centers = np.empty((len(sel), 3 + per_field, 2))
            centers[:, 0] = self.ball[fields]
            centers[:, 1:3] = self.goal_centers
            centers[:, 3:] = self.pos.reshape(self.fields, per_field, 2)[fields]
            frames = perceive(
                sensors,
                self.pos[sel],
                self.heading[sel],
                centers - (self.half_sizes + self.cast_radius),
                centers + (self.half_sizes + self.cast_radius),
                self._cast_half,
                self.tags[self.local[sel]],
            )
            for frame, full in zip(frames, self.frames[sensors], strict=True):
                full[sel] = frame

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        frames = self.frames[self.rays[behavior]]
        stacks = self.stacks[behavior]
        return [stack.push(rows, f[rows]) for stack, f in zip(stacks, frames, strict=True)]
