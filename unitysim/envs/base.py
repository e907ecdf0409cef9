"""The contract between the unitysim player and its environments.

An environment is plain numpy: it never sees protobuf, gRPC or side-channel bytes. The
player (``unitysim.player``) asks it to ``reset()`` or ``step(actions)`` and gets back, per
behavior, one :class:`AgentInfos` batch: the rows Unity would put in that behavior's
``ListAgentInfoProto`` for one message, in message order. A row with ``done`` set is a
terminal info; the same agent id may follow it with a non-done row (terminal and
requesting a decision in one step). ``step`` receives, per behavior, actions whose rows
follow the non-done rows that behavior reported last, which is how Unity maps actions.

Environments are batched over agents (no per-agent Python loops in the hot path),
deterministic given their ``rng``, and read tunables through :class:`Parameters`, which
the EnvironmentParameters side channel fills.
"""

from __future__ import annotations

import functools
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from enum import IntEnum
from typing import ClassVar

import numpy as np

# DimensionProperty flags and observation types as on the wire.
NONE_DIM = 1
TRANSLATIONAL = 2
DEFAULT_OBS = 0
GOAL_SIGNAL = 1


class StatsMethod(IntEnum):
    """Aggregation methods of the Stats side channel."""

    AVERAGE = 0
    MOST_RECENT = 1
    SUM = 2
    HISTOGRAM = 3


@dataclass(frozen=True)
class Sensor:
    """One observation of a behavior, as Unity's ``ObservationSpec`` describes it."""

    name: str
    shape: tuple[int, ...]
    dimension_properties: tuple[int, ...]
    observation_type: int = DEFAULT_OBS
    png: bool = False  # rank-3 sensors sent as concatenated RGB PNGs (camera/grid sensors)
    # a camera: Unity renders it, so a player started with -nographics sends it blank
    # (grid sensors are computed, not rendered)
    rendered: bool = False
    # a StackingSensor over a PNG sensor: its frames' PNGs one after the other and the
    # channel mapping Unity's StackingSensor sends with them
    stacks: int = 1

    @property
    def channel_mapping(self) -> tuple[int, ...]:
        """``compressed_channel_mapping`` as Unity's ``StackingSensor`` writes it: each
        frame's channels padded with -1 to a multiple of 3 (a whole number of PNGs), the
        frames' channels numbered on. Empty for a sensor that stacks nothing."""
        if self.stacks == 1:
            return ()
        channels = self.shape[0] // self.stacks
        padded = -(-channels // 3) * 3
        return tuple(
            frame * channels + c if c < channels else -1
            for frame in range(self.stacks)
            for c in range(padded)
        )

    @classmethod
    def vector(cls, name: str, size: int, observation_type: int = DEFAULT_OBS) -> Sensor:
        return cls(name, (size,), (NONE_DIM,), observation_type)

    @classmethod
    def visual(cls, name: str, channels: int, height: int, width: int, png: bool = True) -> Sensor:
        """A grid sensor (computed, not rendered); ``camera`` for a rendered one."""
        return cls(
            name, (channels, height, width), (NONE_DIM, TRANSLATIONAL, TRANSLATIONAL), png=png
        )

    @classmethod
    def camera(cls, name: str, channels: int, height: int, width: int) -> Sensor:
        return replace(cls.visual(name, channels, height, width), rendered=True)


@dataclass(frozen=True)
class Behavior:
    """A behavior as Unity announces it: fully qualified name and action spec."""

    name: str  # "<BehaviorName>?team=<id>"
    sensors: tuple[Sensor, ...]
    continuous: int = 0
    branches: tuple[int, ...] = ()

    @property
    def mask_size(self) -> int:
        return int(sum(self.branches))


@dataclass
class AgentInfos:
    """The infos of one behavior in one message; every array has the agents on axis 0."""

    agent_id: np.ndarray  # int32 (n,)
    obs: list[np.ndarray]  # one float32 (n, *sensor.shape) per sensor; PNG sensors in [0, 1]
    reward: np.ndarray  # float32 (n,), gathered since the agent's previous info
    done: np.ndarray  # bool (n,)
    max_step_reached: np.ndarray  # bool (n,), done by MaxStep / interruption
    group_id: np.ndarray  # int32 (n,), 0 = no group
    group_reward: np.ndarray  # float32 (n,)
    action_mask: np.ndarray | None = None  # bool (n, sum(branches)), True = NOT allowed

    def __len__(self) -> int:
        return len(self.agent_id)

    @classmethod
    def build(
        cls,
        agent_id: np.ndarray,
        obs: list[np.ndarray],
        reward: np.ndarray | float = 0.0,
        done: np.ndarray | bool = False,
        max_step_reached: np.ndarray | bool = False,
        group_id: np.ndarray | int = 0,
        group_reward: np.ndarray | float = 0.0,
        action_mask: np.ndarray | None = None,
    ) -> AgentInfos:
        """Broadcast scalars to ``n`` rows and fix dtypes once, at the boundary.

        The per-agent arrays are fresh copies (an environment may reuse its own buffers
        right after); observations and masks are taken as they are when their dtype is
        already right. This runs for every message, so the common cases (a scalar, or an
        array of the right dtype and length) take the cheapest numpy call.
        """
        ids = np.asarray(agent_id, dtype=np.int32)
        if ids.ndim != 1:
            ids = ids.reshape(-1)
        n = len(ids)
        return cls(
            agent_id=ids,
            obs=[_observation_rows(o, n) for o in obs],
            reward=_rows(reward, np.float32, n),
            done=_rows(done, np.bool_, n),
            max_step_reached=_rows(max_step_reached, np.bool_, n),
            group_id=_rows(group_id, np.int32, n),
            group_reward=_rows(group_reward, np.float32, n),
            action_mask=None if action_mask is None else np.asarray(action_mask, dtype=np.bool_),
        )

    @staticmethod
    def concat(parts: list[AgentInfos]) -> AgentInfos:
        """Rows of several batches in order (e.g. terminal infos, then decisions)."""
        parts = [p for p in parts if len(p)] or parts[:1]
        masks = [p.action_mask for p in parts]
        return AgentInfos(
            agent_id=np.concatenate([p.agent_id for p in parts]),
            obs=[np.concatenate(sensor) for sensor in zip(*(p.obs for p in parts), strict=True)],
            reward=np.concatenate([p.reward for p in parts]),
            done=np.concatenate([p.done for p in parts]),
            max_step_reached=np.concatenate([p.max_step_reached for p in parts]),
            group_id=np.concatenate([p.group_id for p in parts]),
            group_reward=np.concatenate([p.group_reward for p in parts]),
            action_mask=None if any(m is None for m in masks) else np.concatenate(masks),
        )


def _rows(value: np.ndarray | float | bool, dtype: type, n: int) -> np.ndarray:
    """``value`` as (n,) array of ``dtype`` that nobody else writes: arrays are copied,
    scalars broadcast (to a shared read-only array: most fields are constant)."""
    if isinstance(value, np.ndarray):
        if value.shape == (n,):
            return value.astype(dtype)  # always a copy
    elif isinstance(value, (bool, int, float)) and math.copysign(1.0, value) > 0:
        return _constant_rows(value, dtype, n)  # (-0.0 == 0.0 would share a cache entry)
    return np.broadcast_to(np.asarray(value, dtype=dtype), (n,)).copy()


@functools.lru_cache(maxsize=256)
def _constant_rows(value: float, dtype: type, n: int) -> np.ndarray:
    rows = np.full(n, value, dtype=dtype)
    rows.flags.writeable = False
    return rows


def _observation_rows(obs: np.ndarray, n: int) -> np.ndarray:
    """One sensor's batch as float32 (n, *shape), without a copy when it already is one."""
    if isinstance(obs, np.ndarray) and obs.dtype == np.float32 and obs.shape[:1] == (n,):
        return obs
    return np.asarray(obs, dtype=np.float32).reshape(n, *np.shape(obs)[1:])


@dataclass(frozen=True)
class Actions:
    """Actions for the decision rows of one behavior, in the order they were reported."""

    continuous: np.ndarray  # float32 (n, continuous)
    discrete: np.ndarray  # int32 (n, branches)

    def __len__(self) -> int:
        return len(self.continuous)

    @classmethod
    def empty(cls, behavior: Behavior, n: int) -> Actions:
        return cls(
            np.zeros((n, behavior.continuous), dtype=np.float32),
            np.zeros((n, len(behavior.branches)), dtype=np.int32),
        )


Sampler = Callable[[], float]


@dataclass
class Parameters:
    """Environment parameters from Python: fixed values or seeded samplers.

    As ``Academy.Instance.EnvironmentParameters.GetWithDefault``: a sampler gives a fresh
    draw on every ``get``.
    """

    values: dict[str, float | Sampler] = field(default_factory=dict)

    def get(self, key: str, default: float) -> float:
        value = self.values.get(key, default)
        return float(value()) if callable(value) else float(value)


Output = dict[str, AgentInfos]


class SimEnv(ABC):
    """A unitysim environment: every agent of one build, batched per behavior."""

    #: the name used on the command line and for the launcher file (``<name>.x86_64``)
    name: ClassVar[str]
    #: behaviors announced in this order (the order Python lists them in behavior_specs)
    behaviors: ClassVar[tuple[Behavior, ...]]

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        self.rng = rng
        self.num_areas = max(1, int(num_areas))
        self.params = params
        self._stats: list[tuple[str, float, StatsMethod]] = []

    @abstractmethod
    def reset(self) -> Output:
        """Start fresh episodes everywhere; report first decisions (no terminal infos)."""

    @abstractmethod
    def step(self, actions: Mapping[str, Actions]) -> Output:
        """Apply actions, then simulate until an agent needs a decision or is done."""

    def record_stat(
        self, key: str, value: float, method: StatsMethod = StatsMethod.AVERAGE
    ) -> None:
        """Queue a StatsRecorder entry, sent to Python with the next message."""
        self._stats.append((key, float(value), method))

    def drain_stats(self) -> list[tuple[str, float, StatsMethod]]:
        stats, self._stats = self._stats, []
        return stats

    @classmethod
    def behavior(cls, name: str) -> Behavior:
        return next(b for b in cls.behaviors if b.name == name)
