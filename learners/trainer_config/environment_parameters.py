"""The trainer config's ``environment_parameters``, read as mlagents-learn 1.1.0 reads them:
a number, a sampler (``sampler_type`` and ``sampler_parameters``) or a ``curriculum`` of
lessons, each parameter becoming its lessons (one, without a curriculum). Checks end in a
one-line ``ConfigError`` at the dotted key."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from types import MappingProxyType

from batches.parameters import (
    SAMPLER_TYPES,
    UNSEEDED,
    CompletionCriteria,
    Constant,
    Curriculum,
    Gaussian,
    Lesson,
    MultiRangeUniform,
    Uniform,
    Value,
)
from learners.trainer_config.keys import (
    ConfigError,
    float_in,
    int_from,
    parse_number,
    section,
    show,
    unknown_key,
)

log = logging.getLogger(__name__)

SAMPLER_KEYS = {
    "uniform": ("min_value", "max_value"),
    "gaussian": ("mean", "st_dev"),
    "multirangeuniform": ("intervals",),
    "constant": ("value",),
}
CRITERIA_KEYS = (
    "behavior",
    "measure",
    "min_lesson_length",
    "signal_smoothing",
    "threshold",
    "require_reset",
)


def parse_environment_parameters(raw: object) -> Mapping[str, Curriculum]:
    parameters: dict[str, Curriculum] = {}
    for key, value in section("environment_parameters", raw).items():
        path = f"environment_parameters.{key}"
        if isinstance(value, Mapping) and "curriculum" in value:
            for extra in set(value) - {"curriculum"}:
                raise unknown_key(path, extra, {"curriculum"})
            parameters[key] = _curriculum(f"{path}.curriculum", value["curriculum"])
        else:
            parameters[key] = (Lesson(key, _value(path, value)),)
    return MappingProxyType(parameters)


def _value(path: str, raw: object) -> Value:
    """A number, or a sampler as ML-Agents' ``ParameterRandomizationSettings`` takes it."""
    if not isinstance(raw, Mapping):
        return Constant(parse_number(path, raw, "a number, a sampler or a curriculum"))
    for key in raw:
        if key not in ("sampler_type", "sampler_parameters"):
            raise unknown_key(path, key, {"sampler_type", "sampler_parameters", "curriculum"})
    kind = raw.get("sampler_type")
    if kind not in SAMPLER_TYPES:
        raise ConfigError(
            f"{path}.sampler_type: expected one of {', '.join(SAMPLER_TYPES)}, got {show(kind)}"
        )
    if "sampler_parameters" not in raw:
        raise ConfigError(f"{path}: a sampler needs sampler_parameters")
    given = section(f"{path}.sampler_parameters", raw["sampler_parameters"])
    at = f"{path}.sampler_parameters"
    for key in given:
        if key not in (*SAMPLER_KEYS[kind], "seed"):
            raise unknown_key(at, key, {*SAMPLER_KEYS[kind], "seed"})
    seed = int_from(UNSEEDED)(f"{at}.seed", given.get("seed", UNSEEDED))
    number = float_in()
    if kind == "constant":
        return Constant(number(f"{at}.value", given.get("value", 0.0)))
    if kind == "gaussian":
        mean = number(f"{at}.mean", given.get("mean", 1.0))
        st_dev = float_in(0.0)(f"{at}.st_dev", given.get("st_dev", 1.0))
        return Gaussian(mean, st_dev, seed)
    if kind == "uniform":
        low = number(f"{at}.min_value", given.get("min_value", 0.0))
        high = number(f"{at}.max_value", given.get("max_value", 1.0))
        if low > high:
            raise ConfigError(f"{at}: min_value {low:g} is greater than max_value {high:g}")
        return Uniform(low, high, seed)
    return MultiRangeUniform(_intervals(f"{at}.intervals", given.get("intervals")), seed)


def _intervals(path: str, raw: object) -> tuple[tuple[float, float], ...]:
    if raw is None:
        return ((0.0, 1.0),)
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{path}: expected a list of [min, max] pairs, got {show(raw)}")
    intervals = []
    for i, pair in enumerate(raw):
        if not isinstance(pair, list | tuple) or len(pair) != 2:
            raise ConfigError(f"{path}[{i}]: expected [min, max], got {show(pair)}")
        low, high = (parse_number(f"{path}[{i}]", v, "a number") for v in pair)
        if low > high:
            raise ConfigError(f"{path}[{i}]: min {low:g} is greater than max {high:g}")
        intervals.append((low, high))
    return tuple(intervals)


def _curriculum(path: str, raw: object) -> Curriculum:
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{path}: expected a list of lessons, got {show(raw)}")
    lessons = []
    for i, item in enumerate(raw):
        at = f"{path}[{i}]"
        lesson = section(at, item)
        for key in lesson:
            if key not in ("name", "value", "completion_criteria"):
                raise unknown_key(at, key, {"name", "value", "completion_criteria"})
        for key in ("name", "value"):
            if key not in lesson:
                raise ConfigError(f"{at}: a lesson needs a {key}")
        criteria = lesson.get("completion_criteria")
        last = i == len(raw) - 1
        if criteria is None and not last:
            raise ConfigError(f"{at}: a lesson before the last needs completion_criteria")
        if criteria is not None and last:
            log.warning("%s: the last lesson's completion_criteria are ignored", at)
        parsed = None if last else _criteria(f"{at}.completion_criteria", criteria)
        lessons.append(Lesson(str(lesson["name"]), _value(f"{at}.value", lesson["value"]), parsed))
    return tuple(lessons)


def _criteria(path: str, raw: object) -> CompletionCriteria:
    given = section(path, raw)
    for key in given:
        if key not in CRITERIA_KEYS:
            raise unknown_key(path, key, CRITERIA_KEYS)
    if not isinstance(behavior := given.get("behavior"), str) or not behavior:
        raise ConfigError(f"{path}.behavior: expected a behavior name, got {show(behavior)}")
    measure = given.get("measure", "reward")
    if measure not in ("progress", "reward"):
        raise ConfigError(f"{path}.measure: expected progress or reward, got {show(measure)}")
    bounded = float_in(0.0, 1.0) if measure == "progress" else float_in()
    flags = {}
    for key in ("signal_smoothing", "require_reset"):
        value = given.get(key, key == "signal_smoothing")
        if not isinstance(value, bool):
            raise ConfigError(f"{path}.{key}: expected true or false, got {show(value)}")
        flags[key] = value
    return CompletionCriteria(
        behavior=behavior,
        measure=measure,
        min_lesson_length=int_from(0)(
            f"{path}.min_lesson_length", given.get("min_lesson_length", 0)
        ),
        threshold=bounded(f"{path}.threshold", given.get("threshold", 0.0)),
        **flags,
    )
