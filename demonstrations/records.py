"""What a ``.demo`` file holds, as small immutable values: its summary (:class:`DemoMeta`),
its steps (:class:`DemoStep`) and the whole (:class:`Demonstration`).

Arrays are copied and made read-only on construction, so a demonstration read once can be
shared (by a BC or GAIL buffer, by several learners) without anyone changing it under the
others. Nothing here knows protobuf: the file format lives in ``demo_file``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mlagents_envs.base_env import BehaviorSpec


class DemoError(ValueError):
    """A ``.demo`` path that cannot be read or written as asked: one line naming the file.

    A subclass of :class:`ValueError` so that callers validating their input catch it with
    everything else that is wrong with that input; never a protobuf traceback.
    """

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = str(path)
        self.problem = " ".join(problem.split())  # one line, whatever a library said
        super().__init__(f"{self.path}: {self.problem}")


def _frozen(values: Iterable[float] | np.ndarray, dtype: type, ndmin: int = 1) -> np.ndarray:
    array = np.array(values, dtype=dtype, ndmin=ndmin)  # always a copy: the caller keeps theirs
    array.setflags(write=False)
    return array


@dataclass(frozen=True)
class DemoMeta:
    """The summary Unity's recorder writes at the front of the file.

    ``steps`` is the one number ML-Agents' reader relies on (it reads that many records and
    ignores the rest); ``episodes`` and ``mean_reward`` are informational.
    """

    name: str
    steps: int
    episodes: int
    mean_reward: float

    @staticmethod
    def of_steps(name: str, steps: Sequence[DemoStep]) -> DemoMeta:
        """The summary Unity's ``DemonstrationWriter`` would compute for these steps.

        Every reward counts towards the cumulative reward; every done step ends an episode and
        an unfinished last episode counts too (Unity's ``Close`` counts one more even when the
        recording ends on a done step; we do not copy that miscount).
        """
        episodes = sum(s.done for s in steps) + (0 if steps and steps[-1].done else 1)
        total = np.float32(0)  # Unity sums in single precision
        for step in steps:
            total = np.float32(total + np.float32(step.reward))
        return DemoMeta(name, len(steps), episodes, float(total / np.float32(episodes)))


@dataclass(frozen=True, eq=False)
class DemoStep:
    """One recorded agent step: what the agent saw and the action the recorder stored with it.

    ``observations`` follow the behavior spec's sensors (float32, each sensor's shape; PNG
    images decoded to channels-first floats in [0, 1] as ML-Agents decodes them).
    ``interrupted`` is Unity's ``max_step_reached``: the episode was cut by its step limit.
    ``action_mask`` is flat over all discrete branches and True where an action is masked
    (not allowed), as Unity writes it; empty when the step carries no mask.
    """

    observations: tuple[np.ndarray, ...]
    reward: float = 0.0
    done: bool = False
    interrupted: bool = False
    agent_id: int = 0
    action_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    continuous: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    discrete: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    group_id: int = 0
    group_reward: float = 0.0

    def __post_init__(self) -> None:
        fix = object.__setattr__
        fix(self, "observations", tuple(_frozen(o, np.float32, 0) for o in self.observations))
        fix(self, "reward", float(self.reward))
        fix(self, "done", bool(self.done))
        fix(self, "interrupted", bool(self.interrupted))
        fix(self, "agent_id", int(self.agent_id))
        fix(self, "action_mask", _frozen(self.action_mask, np.bool_).ravel())
        fix(self, "continuous", _frozen(self.continuous, np.float32).ravel())
        fix(self, "discrete", _frozen(self.discrete, np.int32).ravel())
        fix(self, "group_id", int(self.group_id))
        fix(self, "group_reward", float(self.group_reward))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, DemoStep):
            return NotImplemented
        scalars = ("reward", "done", "interrupted", "agent_id", "group_id", "group_reward")
        arrays = ("action_mask", "continuous", "discrete")
        return (
            all(getattr(self, n) == getattr(other, n) for n in scalars)
            and all(np.array_equal(getattr(self, n), getattr(other, n)) for n in arrays)
            and len(self.observations) == len(other.observations)
            and all(
                a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
                for a, b in zip(self.observations, other.observations, strict=True)
            )
        )

    __hash__ = None  # type: ignore[assignment]  # equal by value, holds arrays


@dataclass(frozen=True)
class Demonstration:
    """A whole recording of one behavior: its summary, its spec and its steps in file order.

    ``behavior_name`` is the brain name Unity stores (``Name?team=0``); ``behavior_spec`` is
    built as ML-Agents builds it, from the brain parameters and the first step's sensors.
    """

    meta: DemoMeta
    behavior_name: str
    behavior_spec: BehaviorSpec
    steps: tuple[DemoStep, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "steps", tuple(self.steps))

    @staticmethod
    def of_steps(
        name: str, behavior_name: str, spec: BehaviorSpec, steps: Iterable[DemoStep]
    ) -> Demonstration:
        """A demonstration whose summary is computed from its steps (:meth:`DemoMeta.of_steps`)."""
        steps = tuple(steps)
        return Demonstration(DemoMeta.of_steps(name, steps), behavior_name, spec, steps)
