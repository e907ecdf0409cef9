"""Which lesson each environment parameter is in, decided as mlagents-learn's
``EnvironmentParameterManager`` decides it, from all workers' episodes at once.

A lesson ends when its ``completion_criteria`` hold for their behavior: ``progress`` (the
behavior's steps over its ``max_steps``) above ``threshold``, or the mean return of its
latest ``min_lesson_length`` episodes (smoothed 0.25/0.75 with the previous measure when
``signal_smoothing``) above it; either only once that many episodes finished in the
lesson. The driver sends the new values to every worker (``RolloutService
.set_environment_parameters``) and keeps the lesson numbers in every checkpoint, so that
``--resume`` goes on in the same lesson.

The workers report episodes as totals per poll, not one by one, so the latest episodes
are those of the latest polls that hold at least ``min_lesson_length`` of them.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

from batches.contracts import base_name
from batches.parameters import (
    UNSEEDED,
    Constant,
    Curriculum,
    Gaussian,
    Lesson,
    MultiRangeUniform,
    Uniform,
    Value,
    Values,
)
from driver.options import TrainOptions
from learners.trainer_config.settings import RunConfig

log = logging.getLogger(__name__)


def seeded(parameters: Mapping[str, Curriculum], run_seed: int) -> dict[str, Curriculum]:
    """Each sampler without a ``seed`` gets the run's seed plus one per such sampler, in
    the file's order, as mlagents-learn seeds them."""
    offset, result = 0, {}
    for name, lessons in parameters.items():
        given = []
        for lesson in lessons:
            value = lesson.value
            if not isinstance(value, Constant) and value.seed == UNSEEDED:
                value = dataclasses.replace(value, seed=run_seed + offset)
                offset += 1
            given.append(dataclasses.replace(lesson, value=value))
        result[name] = tuple(given)
    return result


def describe(value: Value) -> str:
    """A value in mlagents-learn's words (its samplers' ``__str__``)."""
    if isinstance(value, Constant):
        return f"Float: value={value.value}"
    if isinstance(value, Uniform):
        return f"Uniform sampler: min={value.min_value}, max={value.max_value}"
    if isinstance(value, Gaussian):
        return f"Gaussian sampler: mean={value.mean}, stddev={value.st_dev}"
    assert isinstance(value, MultiRangeUniform)
    return f"MultiRangeUniform sampler: intervals={[list(i) for i in value.intervals]}"


class Returns:
    """The latest ``size`` episode returns of one behavior, as poll totals: (episodes,
    return sum) per poll, the oldest polls dropped while the rest hold ``size``."""

    def __init__(self, size: int) -> None:
        self.size = max(size, 1)
        self._polls: deque[tuple[int, float]] = deque()
        self._episodes = 0

    def add(self, episodes: int, returns: float) -> None:
        if episodes <= 0:
            return
        self._polls.append((episodes, returns))
        self._episodes += episodes
        while self._episodes - self._polls[0][0] >= self.size:
            self._episodes -= self._polls.popleft()[0]

    def __len__(self) -> int:
        """Episodes held, at most ``size`` (as ML-Agents' reward buffer, a bounded deque)."""
        return min(self._episodes, self.size)

    def mean(self) -> float:
        return sum(r for _, r in self._polls) / self._episodes

    def clear(self) -> None:
        self._polls.clear()
        self._episodes = 0


class LessonPlan:
    def __init__(
        self,
        parameters: Mapping[str, Curriculum],
        run_seed: int,
        max_steps: Callable[[str], int],
        lessons: Mapping[str, int] | None = None,
    ) -> None:
        """``max_steps``: a behavior's own (``--max-steps`` over its config's);
        ``lessons``: where a resumed run was (parameters it does not name start at 0)."""
        self.parameters = seeded(parameters, run_seed)
        self.max_steps = max_steps
        given = dict(lessons or {})
        self.lessons = {
            name: min(int(given.get(name, 0)), len(curriculum) - 1)
            for name, curriculum in self.parameters.items()
        }
        self._smoothed = dict.fromkeys(self.parameters, 0.0)
        sizes: dict[str, int] = {}
        for curriculum in self.parameters.values():
            for lesson in curriculum:
                if (criteria := lesson.completion_criteria) is not None:
                    size = max(sizes.get(criteria.behavior, 1), criteria.min_lesson_length)
                    sizes[criteria.behavior] = size
        self.returns = {behavior: Returns(size) for behavior, size in sizes.items()}
        self._seen: dict[str, tuple[int, float]] = {}  # behavior -> totals at the last poll

    def lesson(self, name: str) -> Lesson:
        return self.parameters[name][self.lessons[name]]

    def values(self) -> Values:
        """Every parameter's value in its current lesson."""
        return {name: self.lesson(name).value for name in self.parameters}

    def log_lessons(self, names: list[str] | None = None) -> None:
        for name in names if names is not None else list(self.parameters):
            lesson = self.lesson(name)
            log.info(
                "Parameter '%s' is in lesson '%s' and has value '%s'.",
                name,
                lesson.name,
                describe(lesson.value),
            )

    def update(
        self, steps: Mapping[str, int], totals: Mapping[str, tuple[int, float, int]]
    ) -> tuple[bool, bool]:
        """Fold in the newest steps and episode totals (keys: behavior ids, teams added
        up); returns (a lesson changed, it asks for a reset)."""
        self._take_episodes(totals)
        behavior_steps: dict[str, int] = {}
        for behavior, count in steps.items():
            name = base_name(behavior)
            behavior_steps[name] = behavior_steps.get(name, 0) + count
        changed, reset = [], False
        for name, curriculum in self.parameters.items():
            number = self.lessons[name]
            criteria = curriculum[number].completion_criteria
            if criteria is None or number + 1 >= len(curriculum):
                continue
            if criteria.behavior not in behavior_steps:
                continue
            returns = self.returns[criteria.behavior]
            if len(returns) < criteria.min_lesson_length:
                continue
            if criteria.measure == "progress":
                progress = behavior_steps[criteria.behavior] / self.max_steps(criteria.behavior)
                done = progress > criteria.threshold
            elif len(returns) < 1:
                continue
            else:
                measure = returns.mean()
                if criteria.signal_smoothing:
                    measure = self._smoothed[name] = 0.25 * self._smoothed[name] + 0.75 * measure
                done = measure > criteria.threshold
            if done:
                self.lessons[name] = number + 1
                changed.append(name)
                reset = reset or criteria.require_reset
        if changed:
            for returns in self.returns.values():  # as mlagents-learn: every reward buffer
                returns.clear()
            self.log_lessons(changed)
        return bool(changed), reset

    def _take_episodes(self, totals: Mapping[str, tuple[int, float, int]]) -> None:
        """The episodes finished since the last poll, per behavior (a restarted worker's
        totals start over: what went back is not counted)."""
        merged: dict[str, tuple[int, float]] = {}
        for behavior, (episodes, returns, _) in totals.items():
            name = base_name(behavior)
            old = merged.get(name, (0, 0.0))
            merged[name] = (old[0] + episodes, old[1] + returns)
        for name, (episodes, returns) in merged.items():
            before = self._seen.get(name, (0, 0.0))
            self._seen[name] = (episodes, returns)
            if name in self.returns and episodes > before[0]:
                self.returns[name].add(episodes - before[0], returns - before[1])


def lesson_plan(
    options: TrainOptions, config: RunConfig, resume: dict[str, Any] | None
) -> LessonPlan:
    """The run's curriculum, in the lessons a resumed run had reached."""
    return LessonPlan(
        config.environment_parameters,
        options.seed,
        lambda behavior: options.max_steps or config.for_behavior(behavior).max_steps,
        (resume or {}).get("meta", {}).get("lessons"),
    )
