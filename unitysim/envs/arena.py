"""Shared machinery of the spec-faithful environments: agents on small 2-D fields, batched.

Why one module: StrikersVsGoalie, SoccerTwos, Walker, Hallway, Pyramids, DungeonEscape,
GridFoodCollector and WallJump reproduce what real example builds announce (behaviors,
sensors, agent and group ids) with simple, learnable rules. Their rules differ, but the
Unity side of them is the same, and lives here once:

- :class:`ArenaEnv`, the Academy loop: a build is ``fields_per_area`` fields (the copies of
  the training area in the example scene) times ``num_areas``; agents are numbered field by
  field from a per-field ``layout`` (behavior, group), as the builds number them. Each
  ``step`` applies the actions to the rows reported last, then runs physics steps until an
  episode ends or a decision is due (every ``decision_period`` steps). Terminal infos come
  before the decisions of the same message, so an agent can be done and ask for its next
  decision at once, as in 3DBall.
- :func:`cast_rays` / :func:`ray_features`: RayPerceptionSensor-like vectors. Rays fan out
  as Unity's (centre first, then right/left pairs); each ray reports a one-hot tag of what
  it hit, a "missed" flag and the hit fraction of its length. Objects are axis-aligned
  boxes; the field's edge is hit when nothing nearer is.
- :class:`FrameStack`: StackingSensor (oldest frame first, zeros after an episode begins).
- :func:`steer` / :func:`drive`: moving agents by forward / right / turn commands; ``AXIS``
  maps a discrete branch value (0 none, 1 plus, 2 minus) to a sign, ``MOVES`` the actions
  of the one-branch examples to commands.
"""

from __future__ import annotations

import functools
import itertools
from abc import abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from unitysim.envs.base import Actions, AgentInfos, Output, Parameters, SimEnv, StatsMethod

DT = 0.02  # Unity's fixed time step
AXIS = np.array([0.0, 1.0, -1.0])  # discrete branch value -> sign
# One-branch movement (Hallway, Pyramids, PushBlock-like DungeonEscape): per action, the
# (forward, right, turn left) command: none, forward, back, turn right, turn left, then
# for 7 actions strafe left and right.
MOVES = np.array(
    [[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 0, -1], [0, 0, 1], [0, -1, 0], [0, 1, 0]],
    dtype=np.float64,
)
FAR = 1.0e4  # where absent objects are put: beyond every field's edge, never hit first
_NO_ROWS = np.zeros(0, dtype=np.intp)


# --- perception ------------------------------------------------------------------------


def ray_offsets(rays_per_direction: int, max_degrees: float) -> np.ndarray:
    """Ray angles relative to the facing direction (radians, counter-clockwise positive),
    in Unity's order: straight ahead, then for each step one ray right and one left."""
    steps = np.arange(1, rays_per_direction + 1) * (max_degrees / max(rays_per_direction, 1))
    return np.radians(np.concatenate([[0.0], np.column_stack([-steps, steps]).ravel()]))


def cast_rays(
    origin: np.ndarray,
    heading: np.ndarray,
    offsets: np.ndarray,
    length: float | np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    half: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Cast ``R`` rays from each of ``n`` origins against ``m`` boxes each.

    ``origin`` (n, 2), ``heading`` (n,), ``offsets`` and ``length`` (R,) or scalar, boxes
    ``lo``/``hi`` (n, m, 2) in the same frame as the field ``[-half, half]``. A box
    containing the origin (the agent itself) is not seen. Returns the hit fraction (n, R)
    in [0, 1] (1 = nothing within ``length``) and what was hit (n, R): box index, ``m``
    for the field's edge, -1 nothing.
    """
    n, m = lo.shape[:2]
    angle = (heading[:, None] + offsets).astype(np.float32)
    dx, dy = np.cos(angle), np.sin(angle)
    np.copyto(dx, 1e-9, where=dx == 0.0)  # float32 cosines are never 0 in practice
    np.copyto(dy, 1e-9, where=dy == 0.0)
    ix, iy = 1.0 / dx, 1.0 / dy  # (n, R)
    # Slab test, (n, m, R): box j is entered at ``near`` if near <= far and near >= 0;
    # the corners relative to the origin, lo then hi: (n, 2m) per axis
    rel = (np.concatenate([lo, hi], axis=1) - origin[:, None, :]).astype(np.float32)
    tx = np.ascontiguousarray(rel[:, :, 0])[:, :, None] * ix[:, None, :]
    ty = np.ascontiguousarray(rel[:, :, 1])[:, :, None] * iy[:, None, :]
    tx1, tx2, ty1, ty2 = tx[:, :m], tx[:, m:], ty[:, :m], ty[:, m:]
    near = np.maximum(np.minimum(tx1, tx2), np.minimum(ty1, ty2))
    far = np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2))
    np.putmask(near, (near > far) | (near < 0.0), np.inf)
    best = near.argmin(axis=1)
    t_best = near[np.arange(n)[:, None], best, np.arange(best.shape[1])]
    # where the ray leaves the field: at half * |1/d| - origin / d along each axis
    o = origin.astype(np.float32)
    edge = np.minimum(
        half[0] * np.abs(ix) - o[:, 0, None] * ix, half[1] * np.abs(iy) - o[:, 1, None] * iy
    )
    hit = np.where(t_best < edge, best, m)
    frac = np.minimum(t_best, edge) / np.asarray(length, dtype=np.float32)
    return np.minimum(frac, 1.0), np.where(frac <= 1.0, hit, -1)


def ray_tags(hit: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Tag index of each hit: ``table`` (n, m + 1), last entry for the edge; -1 for no hit
    (or an untagged object)."""
    tags = table[np.arange(len(hit))[:, None], hit]  # hit -1 reads the edge; masked below
    return np.where(hit >= 0, tags, -1)


def ray_features(tag: np.ndarray, frac: np.ndarray, num_tags: int) -> np.ndarray:
    """RayPerceptionOutput as floats: per ray, one-hot tag, missed flag, hit fraction."""
    n, rays = tag.shape
    out = np.empty((n, rays, num_tags + 2), dtype=np.float32)
    np.equal(tag[:, :, None], np.arange(num_tags), out=out[:, :, :num_tags], casting="unsafe")
    out[:, :, num_tags] = frac >= 1.0
    out[:, :, num_tags + 1] = frac
    return out.reshape(n, -1)


@dataclass(frozen=True)
class Rays:
    """One RayPerceptionSensor: its fan of rays, their length and how many tags it detects."""

    rays_per_direction: int
    max_degrees: float
    length: float
    num_tags: int
    backward: bool = False  # the "Reverse" sensors look behind the agent

    @property
    def count(self) -> int:
        return 2 * self.rays_per_direction + 1

    @property
    def offsets(self) -> np.ndarray:
        offsets = ray_offsets(self.rays_per_direction, self.max_degrees)
        return offsets + np.pi if self.backward else offsets

    @property
    def size(self) -> int:
        return self.count * (self.num_tags + 2)


@functools.cache
def _fan(sensors: tuple[Rays, ...]) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    """Offsets and lengths of all rays of ``sensors``, and where each sensor's rays start."""
    offsets = np.concatenate([s.offsets for s in sensors])
    lengths = np.concatenate([np.full(s.count, s.length) for s in sensors])
    return offsets, lengths, tuple(np.cumsum([0] + [s.count for s in sensors]).tolist())


def perceive(
    sensors: tuple[Rays, ...],
    origin: np.ndarray,
    heading: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    half: tuple[float, float],
    table: np.ndarray | tuple[np.ndarray, ...],
) -> list[np.ndarray]:
    """The feature vectors of several ray sensors that see the same boxes, cast at once.

    ``table`` (n, m + 1) maps box index (and last, the edge) to a tag, -1 for none; a tuple
    gives one table per sensor (sensors that see the same things differently)."""
    offsets, lengths, starts = _fan(sensors)
    frac, hit = cast_rays(origin, heading, offsets, lengths, lo, hi, half)
    if isinstance(table, tuple):
        tags = np.concatenate(
            [
                ray_tags(hit[:, a:b], t)
                for (a, b), t in zip(itertools.pairwise(starts), table, strict=True)
            ],
            axis=1,
        )
    else:
        tags = ray_tags(hit, table)
    n, widths = len(tags), {s.num_tags for s in sensors}
    if len(widths) > 1:
        return [
            ray_features(tags[:, a:b], frac[:, a:b], s.num_tags)
            for (a, b), s in zip(itertools.pairwise(starts), sensors, strict=True)
        ]
    (width,) = widths  # one encoding for all rays, then split per sensor
    features = ray_features(tags, frac, width).reshape(n, -1, width + 2)
    return [features[:, a:b].reshape(n, -1) for a, b in itertools.pairwise(starts)]


class FrameStack:
    """StackingSensor: the last ``frames`` observations of each agent, oldest first."""

    def __init__(self, n: int, frames: int, size: int) -> None:
        self.size = size
        self.buffer = np.zeros((n, frames * size), dtype=np.float32)

    def push(self, rows: np.ndarray, frame: np.ndarray) -> np.ndarray:
        stacked = np.concatenate([self.buffer[rows, self.size :], frame], axis=1)
        self.buffer[rows] = stacked
        return stacked

    def clear(self, which: np.ndarray) -> None:
        self.buffer[which] = 0.0


# --- movement --------------------------------------------------------------------------


def steer(
    forward: np.ndarray, right: np.ndarray, turn: np.ndarray, speed: float, turn_speed: float
) -> tuple[np.ndarray, np.ndarray]:
    """Commands (each in [-1, 1]) as what one physics step does: the displacement in the
    agent's own frame as a complex number (ahead + 1j * left) and the turn (radians,
    counter-clockwise), for :func:`drive`."""
    return (forward - 1j * right) * (speed * DT), turn * (turn_speed * DT)


def limits(half: tuple[float, float], radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The corners between which the centre of an agent of ``radius`` stays."""
    high = np.array([half[0] - radius, half[1] - radius])
    return -high, high


def drive(
    pos: np.ndarray,
    heading: np.ndarray,
    motion: np.ndarray,
    turn: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
) -> None:
    """One physics step of :func:`steer`'s commands, in place; ``pos`` (n, 2) float64
    stays within ``low``/``high``. Headings are not wrapped (only used through sines)."""
    pos.view(np.complex128)[:, 0] += np.exp(1j * heading) * motion
    np.maximum(pos, low, out=pos)
    np.minimum(pos, high, out=pos)
    heading += turn


def overlaps(pos: np.ndarray, radius: float, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(n, m): does the square of half size ``radius`` around each ``pos`` (n, 2) touch
    box j (``lo``/``hi`` (n, m, 2) or (m, 2))?"""
    p = pos[:, None, :]
    inside = (p + radius > lo) & (p - radius < hi)
    return inside[..., 0] & inside[..., 1]


def uniform_in(
    rng: np.random.Generator, k: int, half: tuple[float, float], margin: float
) -> np.ndarray:
    """``k`` random points in the field, ``margin`` away from its edge."""
    return rng.uniform(-1.0, 1.0, size=(k, 2)) * (np.asarray(half) - margin)


# --- the Academy loop ------------------------------------------------------------------


class ArenaEnv(SimEnv):
    """Agents on ``fields_per_area * num_areas`` fields; subclasses write the rules.

    Per agent (axis 0 of every array, "rows"): ``ids``, behavior index ``beh``, ``field``,
    ``group`` id, ``alive`` and the ``reward`` / ``group_reward`` gathered since its last
    info. Subclasses implement ``_begin`` (OnEpisodeBegin), ``_act`` (store actions),
    ``_simulate`` (one physics step) and ``_observe`` (sensors), optionally ``_perceive``
    (sensing shared by behaviors), ``_mask`` and ``_ended`` (what follows an episode end;
    by default the next episode begins).
    """

    decision_period: ClassVar[int] = 5
    fields_per_area: ClassVar[int] = 1
    #: per agent of one field: (behavior index, group within the field; 0 = no group)
    layout: ClassVar[tuple[tuple[int, int], ...]] = ((0, 0),)

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.fields = self.fields_per_area * self.num_areas
        behavior, group = (np.array(column) for column in zip(*self.layout, strict=True))
        per_field = len(behavior)
        self.n = per_field * self.fields
        self.field = np.repeat(np.arange(self.fields), per_field)
        self.local = np.tile(np.arange(per_field), self.fields)  # index within the field
        self.beh = np.tile(behavior, self.fields)
        local = np.tile(group, self.fields)
        self.group = np.where(local > 0, self.field * group.max() + local, 0).astype(np.int32)
        self.ids = np.arange(self.n, dtype=np.int32)
        self.next_id = self.n
        self.alive = np.ones(self.n, dtype=bool)
        # Planar kinematics of every agent (see ``steer`` and ``drive``).
        self.pos = np.zeros((self.n, 2))
        self.heading = np.zeros(self.n)
        self.motion = np.zeros(self.n, dtype=complex)  # per physics step, see ``steer``
        self.turn = np.zeros(self.n)
        self.reward = np.zeros(self.n)
        self.group_reward = np.zeros(self.n)
        self.episode_steps = np.zeros(self.n, dtype=np.int64)
        self.field_steps = np.zeros(self.fields, dtype=np.int64)
        self.academy_steps = 0
        self._requested: list[np.ndarray] = [_NO_ROWS] * len(self.behaviors)

    # --- rules, written by subclasses --------------------------------------------------

    @abstractmethod
    def _begin(self, which: np.ndarray) -> None:
        """OnEpisodeBegin of the agents in ``which`` (bool, (n,))."""

    @abstractmethod
    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        """Store the actions of ``rows``; they act on every physics step until replaced."""

    @abstractmethod
    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        """One FixedUpdate; returns (episode ended, of those: interrupted), bool (n,)."""

    @abstractmethod
    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        """The sensors of ``behavior`` for ``rows`` (all of that behavior)."""

    def _perceive(self, rows: np.ndarray) -> None:
        """Called before ``_observe`` with the rows of every behavior of one batch of
        infos: work shared across behaviors (ray casts for all agents at once) goes here."""

    def _mask(self, behavior: int, rows: np.ndarray) -> np.ndarray:
        """Action mask of decision rows, True = forbidden; nothing masked by default."""
        return np.zeros((len(rows), self.behaviors[behavior].mask_size), dtype=bool)

    def _ended(self, ended: np.ndarray, interrupted: np.ndarray) -> None:
        """After the terminal infos of ``ended``: by default their next episodes begin."""
        self._start(ended)

    # --- helpers for subclasses ---------------------------------------------------------

    def _start(self, which: np.ndarray) -> None:
        self.episode_steps[which] = 0
        self._begin(which)

    def _renew_ids(self, which: np.ndarray) -> None:
        """Give the agents in ``which`` fresh ids (a re-enabled Agent is a new agent)."""
        k = int(which.sum())
        self.ids[which] = np.arange(self.next_id, self.next_id + k, dtype=np.int32)
        self.next_id += k

    # --- the contract -------------------------------------------------------------------

    def reset(self) -> Output:
        self._restart_all()
        return self._output(None, self._infos(self.alive))

    def _restart_all(self) -> None:
        """``Academy.ForcedFullReset``: every agent back (disabled ones as new agents)."""
        self.academy_steps = 0
        self.reward[:] = 0.0
        self.group_reward[:] = 0.0
        self._renew_ids(~self.alive)
        self.alive[:] = True
        self.field_steps[:] = 0
        self._start(np.ones(self.n, dtype=bool))

    def step(self, actions: Mapping[str, Actions]) -> Output:
        for b, behavior in enumerate(self.behaviors):
            rows, act = self._requested[b], actions.get(behavior.name)
            if act is None or len(act) == 0 or len(rows) == 0:
                continue
            if len(act) != len(rows):
                raise ValueError(
                    f"{behavior.name}: {len(act)} actions for {len(rows)} decision rows"
                )
            self._act(rows, act)
        self._requested = [_NO_ROWS] * len(self.behaviors)
        while True:
            self.academy_steps += 1
            self.episode_steps += 1
            self.field_steps += 1
            ended, interrupted = self._simulate()
            ended = ended & self.alive
            terminal = None
            if ended.any():
                terminal = self._infos(ended, done=True, interrupted=interrupted)
                self._ended(ended, interrupted & ended)
            if self.academy_steps % self.decision_period == 0:
                return self._output(terminal, self._infos(self.alive))
            if terminal is not None:
                return self._output(terminal, None)

    # --- building infos -----------------------------------------------------------------

    def _infos(
        self, which: np.ndarray, done: bool = False, interrupted: np.ndarray | bool = False
    ) -> list[tuple[np.ndarray, AgentInfos] | None]:
        """Per behavior: the rows of ``which`` under it and their infos (rewards drained)."""
        interrupted = np.broadcast_to(np.asarray(interrupted, dtype=bool), (self.n,))
        self._perceive(np.flatnonzero(which))
        out: list[tuple[np.ndarray, AgentInfos] | None] = []
        for b, behavior in enumerate(self.behaviors):
            rows = np.flatnonzero(which & (self.beh == b))
            if len(rows) == 0:
                out.append(None)
                continue
            mask = None
            if behavior.branches:
                mask = (
                    np.zeros((len(rows), behavior.mask_size), dtype=bool)
                    if done
                    else self._mask(b, rows)
                )
            infos = AgentInfos.build(
                self.ids[rows],
                self._observe(b, rows),
                reward=self.reward[rows],
                done=done,
                max_step_reached=interrupted[rows] if done else False,
                group_id=self.group[rows],
                group_reward=self.group_reward[rows],
                action_mask=mask,
            )
            self.reward[rows] = 0.0
            self.group_reward[rows] = 0.0
            out.append((rows, infos))
        return out

    def _output(
        self,
        terminal: list[tuple[np.ndarray, AgentInfos] | None] | None,
        decisions: list[tuple[np.ndarray, AgentInfos] | None] | None,
    ) -> Output:
        result: Output = {}
        for b, behavior in enumerate(self.behaviors):
            done = terminal[b] if terminal else None
            decide = decisions[b] if decisions else None
            parts = [part[1] for part in (done, decide) if part is not None]
            if len(parts) == 2:
                result[behavior.name] = AgentInfos.concat(parts)
            else:
                result[behavior.name] = parts[0] if parts else self._empty(b)
            self._requested[b] = decide[0] if decide is not None else _NO_ROWS
        return result

    def _empty(self, b: int) -> AgentInfos:
        behavior = self.behaviors[b]
        return AgentInfos.build(
            np.zeros(0, dtype=np.int32),
            [np.zeros((0, *s.shape), dtype=np.float32) for s in behavior.sensors],
            action_mask=np.zeros((0, behavior.mask_size), dtype=bool)
            if behavior.branches
            else None,
        )


# --- ball games: SoccerTwos, StrikersVsGoalie ------------------------------------------


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
        self.ball_radius, self.friction, self.ball_touch = 0.375, 3.4, 0.0
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

    def _begin(self, which: np.ndarray) -> None:
        """Field reset (``ResetScene``): every agent of the field to its start, ball near
        the centre; the rows of a field always end their episodes together."""
        fields = np.zeros(self.fields, dtype=bool)
        fields[self.field[which]] = True
        rows = fields[self.field]
        k, f = int(rows.sum()), int(fields.sum())
        self.ball_radius = 0.05 * self.params.get("ball_scale", 7.5)
        self.friction = 0.35 * self.params.get("gravity", 9.81)
        self.ball_touch = self.params.get("ball_touch", 0.0)
        self.ball_limit = np.asarray(self.half) - self.ball_radius
        start = np.asarray(self.start)[self.local[rows]]
        self.pos[rows] = start[:, :2] + self.rng.uniform(-0.5, 0.5, size=(k, 2))
        self.heading[rows] = start[:, 2] + self.rng.uniform(-0.3, 0.3, size=k)
        self.motion[rows] = 0.0
        self.turn[rows] = 0.0
        self.ball[fields] = self.rng.uniform(-1.0, 1.0, size=(f, 2))
        self.ball_vel[fields] = 0.0
        self.field_steps[fields] = 0
        self.episode_steps[rows] = 0
        for stacks in self.stacks:
            for stack in stacks:
                stack.clear(rows)

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        c = AXIS[np.clip(actions.discrete, 0, 2)]  # forward, right, turn left
        self.motion[rows], self.turn[rows] = steer(
            c[:, 0], c[:, 1], c[:, 2], self.speed, self.turn_speed
        )

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        drive(self.pos, self.heading, self.motion, self.turn, self.low, self.high)
        scored = self._roll_ball()
        self._rewards(scored)
        ended = (scored != 0) | (self.field_steps >= self.max_env_steps)
        return ended[self.field], (ended & (scored == 0))[self.field]

    def _roll_ball(self) -> np.ndarray:
        """Kicks, rolling and bounces of one step; returns +1 / -1 per field for a goal
        at +x / -x, else 0."""
        per_field = len(self.layout)
        pos = self.pos.reshape(self.fields, per_field, 2)
        rel = self.ball[:, None, :] - pos
        dist2 = np.einsum("fpk,fpk->fp", rel, rel)
        reach = self.agent_radius + self.ball_radius
        touch = dist2 < reach * reach
        if touch.any():
            kicked = np.flatnonzero(touch.any(axis=1))
            kicker = touch[kicked].argmax(axis=1)
            row = kicked * per_field + kicker
            away = rel[kicked, kicker] / np.sqrt(np.maximum(dist2[kicked, kicker], 1e-12))[:, None]
            power = np.where(self.motion[row].real > 0, 8.0, 2.0)  # moving forward: a kick
            self.ball[kicked] = pos[kicked, kicker] + away * reach
            self.ball_vel[kicked] = away * power[:, None]
            self.reward[row] += 0.2 * self.ball_touch
        speed = np.sqrt(np.einsum("fk,fk->f", self.ball_vel, self.ball_vel))
        self.ball_vel *= np.maximum(0.0, 1.0 - self.friction * DT / (speed + 1e-9))[:, None]
        self.ball += self.ball_vel * DT
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
                centers - self.half_sizes,
                centers + self.half_sizes,
                self.half,
                self.tags[self.local[sel]],
            )
            for frame, full in zip(frames, self.frames[sensors], strict=True):
                full[sel] = frame

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        frames = self.frames[self.rays[behavior]]
        stacks = self.stacks[behavior]
        return [stack.push(rows, f[rows]) for stack, f in zip(stacks, frames, strict=True)]
