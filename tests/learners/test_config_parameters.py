"""environment_parameters as mlagents-learn 1.1.0 reads them: every anchor config that has
them parses, each kind of value, and a wrong one is one line naming the key."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from batches.parameters import UNSEEDED, Constant, Gaussian, MultiRangeUniform, Uniform
from learners.trainer_config.keys import ConfigError
from learners.trainer_config.parse import load_config, parse_config

ANCHORS = Path(__file__).resolve().parents[1] / "mlagents_configs" / "ppo"


def parameters(text: str):
    return parse_config(yaml.safe_load(text)).environment_parameters


def test_the_anchor_configs_with_parameters_parse_with_nothing_reported():
    randomize = load_config(ANCHORS / "3DBall_randomize.yaml")
    assert randomize.unsupported == ()
    assert [lesson.value for lesson in randomize.environment_parameters["mass"]] == [
        Uniform(0.5, 10.0, UNSEEDED)
    ]
    curriculum = load_config(ANCHORS / "WallJump_curriculum.yaml")
    assert curriculum.unsupported == ()
    big = curriculum.environment_parameters["big_wall_height"]
    assert [lesson.name for lesson in big] == ["Lesson0", "Lesson1", "Lesson2", "Lesson3"]
    assert big[1].value == Uniform(4.0, 7.0, UNSEEDED) and big[3].value == Constant(8.0)
    criteria = big[0].completion_criteria
    assert criteria is not None and big[3].completion_criteria is None
    assert (criteria.behavior, criteria.measure, criteria.threshold) == (
        "BigWallJump",
        "progress",
        0.1,
    )
    assert (criteria.min_lesson_length, criteria.signal_smoothing) == (100, True)


def test_every_sampler_type_with_mlagents_defaults_and_seeds():
    got = parameters("""
environment_parameters:
  a: {sampler_type: uniform, sampler_parameters: {max_value: 3}}
  b: {sampler_type: gaussian, sampler_parameters: {mean: 2, st_dev: 0.5, seed: 7}}
  c: {sampler_type: multirangeuniform, sampler_parameters: {intervals: [[1, 2], [5, 6]]}}
  d: {sampler_type: constant, sampler_parameters: {value: 4}}
  e: 2.5e-1
""")
    assert {k: v[0].value for k, v in got.items()} == {
        "a": Uniform(0.0, 3.0, UNSEEDED),
        "b": Gaussian(2.0, 0.5, 7),
        "c": MultiRangeUniform(((1.0, 2.0), (5.0, 6.0)), UNSEEDED),
        "d": Constant(4.0),
        "e": Constant(0.25),
    }


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("{sampler_type: beta, sampler_parameters: {}}", r"\.x\.sampler_type: expected one of"),
        ("{sampler_type: uniform}", r"\.x: a sampler needs sampler_parameters"),
        (
            "{sampler_type: uniform, sampler_parameters: {min_value: 3, max_value: 1}}",
            r"min_value 3 is greater than max_value 1",
        ),
        (
            "{sampler_type: uniform, sampler_parameters: {min_valeu: 3}}",
            r"sampler_parameters\.min_valeu: unknown key; did you mean 'min_value'",
        ),
        (
            "{sampler_type: multirangeuniform, sampler_parameters: {intervals: [[1, 2, 3]]}}",
            r"intervals\[0\]: expected \[min, max\]",
        ),
        ("{curriculum: []}", r"\.x\.curriculum: expected a list of lessons"),
        (
            "{curriculum: [{name: A, value: 1}, {name: B, value: 2}]}",
            r"curriculum\[0\]: a lesson before the last needs completion_criteria",
        ),
        (
            "{curriculum: [{name: A, value: 1, completion_criteria: {measure: reward}}, "
            "{name: B, value: 2}]}",
            r"completion_criteria\.behavior: expected a behavior name",
        ),
        (
            "{curriculum: [{name: A, value: 1, completion_criteria: {behavior: W, "
            "measure: progress, threshold: 1.5}}, {name: B, value: 2}]}",
            r"completion_criteria\.threshold: expected a number in \[0, 1\]",
        ),
        (
            "{curriculum: [{name: A, value: 1, completion_criteria: {behavior: W, "
            "min_lesson_lenght: 3}}, {name: B, value: 2}]}",
            r"unknown key; did you mean 'min_lesson_length'",
        ),
        ("{curriculum: [{name: A}]}", r"curriculum\[0\]: a lesson needs a value"),
    ],
)
def test_a_wrong_parameter_is_one_line_naming_its_key(value: str, message: str):
    with pytest.raises(ConfigError, match=r"^environment_parameters\.x") as caught:
        parameters(f"environment_parameters:\n  x: {value}\n")
    assert "\n" not in str(caught.value)
    assert caught.match(message)
