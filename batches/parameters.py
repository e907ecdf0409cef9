"""Environment parameters as mlagents-learn sends them: a constant or a sampler the build
draws from at each episode reset, grouped in lessons (a curriculum; one lesson when the
config gives a plain value or sampler).

The driver decides the lesson (``driver/training/curriculum.py``); workers send each lesson's values
to Unity over the EnvironmentParameters side channel (``rollout/environment/unity.py``). Plain
frozen data, so that a lesson travels to Ray workers with a collect.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class Constant:
    value: float


@dataclass(frozen=True)
class Uniform:
    min_value: float
    max_value: float
    seed: int


@dataclass(frozen=True)
class Gaussian:
    mean: float
    st_dev: float
    seed: int


@dataclass(frozen=True)
class MultiRangeUniform:
    intervals: tuple[tuple[float, float], ...]
    seed: int


UNSEEDED = -1  # a sampler without ``seed``: the run's seed, plus one per such sampler
Value = Constant | Uniform | Gaussian | MultiRangeUniform
Values = dict[str, Value]  # parameter name -> what the build draws it from
SAMPLER_TYPES = ("uniform", "gaussian", "multirangeuniform", "constant")


def reseeded(value: Value, offset: int) -> Value:
    """``value`` with its sampler's seed moved by ``offset``: one stream per worker (and
    per player restart), where mlagents-learn gives every environment the same seed."""
    if isinstance(value, Constant):
        return value
    return dataclasses.replace(value, seed=value.seed + offset)


@dataclass(frozen=True)
class CompletionCriteria:
    """When a lesson ends, as ML-Agents' ``CompletionCriteriaSettings``."""

    behavior: str
    measure: Literal["progress", "reward"] = "reward"
    min_lesson_length: int = 0  # episodes of ``behavior`` since the lesson began
    signal_smoothing: bool = True
    threshold: float = 0.0
    require_reset: bool = False


@dataclass(frozen=True)
class Lesson:
    name: str
    value: Value
    completion_criteria: CompletionCriteria | None = None  # None: the last lesson


Curriculum = tuple[Lesson, ...]  # one parameter's lessons, in order


@dataclass(frozen=True)
class Assignment:
    """What every worker sends its build: the values of the current lessons, numbered so
    that a worker (also one Ray restarted) applies each assignment once. ``reset``: the
    lesson change asked for ``require_reset``: rows in progress are dropped, Unity reset."""

    number: int
    values: Values
    reset: bool = False
