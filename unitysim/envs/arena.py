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
- :func:`steer` / :func:`drive`: moving agents by forward / right / turn commands; ``AXIS``
  maps a discrete branch value (0 none, 1 plus, 2 minus) to a sign, ``MOVES`` the actions
  of the one-branch examples to commands; :class:`RigidBodyEnv`, agents that move as Unity
  rigid bodies pushed by those commands (Hallway, Pyramids), kept out of walls by
  :func:`collide`.

What the agents sense (ray casts, frame stacks) is in :mod:`unitysim.envs.perception`; the
rules the two ball games share (SoccerTwos, StrikersVsGoalie) in
:mod:`unitysim.envs.ball_game`.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Mapping
from typing import ClassVar

import numpy as np

from unitysim.envs.base import Actions, AgentInfos, Output, Parameters, SimEnv

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


def stop_at_edge(
    pos: np.ndarray, velocity: np.ndarray, edge: tuple[np.ndarray, np.ndarray]
) -> None:
    """Bodies (``pos``, ``velocity`` (n, 2), in place) past the field's ``edge``
    (:func:`limits`) are put back on it and lose their velocity across it."""
    low, high = edge
    velocity[(pos < low) | (pos > high)] = 0.0
    np.clip(pos, low, high, out=pos)


def collide(
    pos: np.ndarray,
    velocity: np.ndarray,
    edge: tuple[np.ndarray, np.ndarray],
    centres: np.ndarray,
    halves: np.ndarray,
    radius: float,
) -> None:
    """Agents (``pos``, ``velocity`` (n, 2), in place) of ``radius`` that went past the
    field's ``edge`` (:func:`limits`) or into one of the boxes (``centres`` (n, m, 2),
    ``halves`` (m, 2) or (n, m, 2)) are put back out along the axis they went in least and
    lose their velocity along it: they slide along the side, as a rigid body along a static
    collider."""
    stop_at_edge(pos, velocity, edge)
    gap = np.abs(pos[:, None, :] - centres) - (halves + radius)  # (n, m, 2)
    inside = (gap < 0).all(axis=2)
    if not inside.any():
        return
    rows, which = np.nonzero(inside)
    axis = gap[rows, which].argmax(axis=1)  # the shallower way out
    side = np.sign(pos[rows, axis] - centres[rows, which, axis])
    pos[rows, axis] -= side * gap[rows, which, axis]
    velocity[rows, axis] = 0.0


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


class RigidBodyEnv(ArenaEnv):
    """Agents that are Unity rigid bodies driven by one branch of ``MOVES`` (Hallway,
    Pyramids): forward or back adds a velocity change of ``push_change`` a physics step
    along the facing (ForceMode.VelocityChange), linear ``drag`` slows it, a turn is
    ``turn_rate`` radians a second. ``velocity`` (n, 2) is per second in the world's frame
    (a turn does not carry it round); subclasses keep it out of walls (:func:`collide`)."""

    push_change: ClassVar[float]
    drag: ClassVar[float]
    turn_rate: ClassVar[float]

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.velocity = np.zeros((self.n, 2))
        self.push = np.zeros(self.n)  # the stored action: +1 forward, -1 back, 0 none

    def _stand(self, which: np.ndarray) -> None:
        """At an episode's begin: at rest, no action stored."""
        self.velocity[which] = 0.0
        self.push[which] = 0.0
        self.turn[which] = 0.0

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        c = MOVES[np.clip(actions.discrete[:, 0], 0, 4)]
        self.push[rows], self.turn[rows] = c[:, 0], c[:, 2] * self.turn_rate * DT

    def _glide(self) -> None:
        """One physics step of every body, before collisions."""
        self.heading += self.turn
        facing = np.column_stack([np.cos(self.heading), np.sin(self.heading)])
        self.velocity += self.push_change * self.push[:, None] * facing
        self.velocity /= 1.0 + self.drag * DT
        self.pos += self.velocity * DT
