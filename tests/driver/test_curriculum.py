"""Lessons decided as mlagents-learn's EnvironmentParameterManager decides them, from the
workers' episode totals: progress and reward measures, min_lesson_length, smoothing, the
reward window cleared at each change, seeds, and resume."""

from __future__ import annotations

import logging

import pytest

from batches.parameters import (
    UNSEEDED,
    CompletionCriteria,
    Constant,
    Gaussian,
    Lesson,
    Uniform,
)
from driver.training.curriculum import LessonPlan, Returns, seeded


def lessons(criteria: CompletionCriteria, values: tuple[float, ...] = (1.0, 2.0, 3.0)):
    last = len(values) - 1
    return tuple(
        Lesson(f"L{i}", Constant(v), None if i == last else criteria) for i, v in enumerate(values)
    )


def plan(criteria: CompletionCriteria, max_steps: int = 1000, **kw) -> LessonPlan:
    return LessonPlan({"wall": lessons(criteria)}, 0, lambda behavior: max_steps, **kw)


def test_progress_moves_on_past_the_threshold_once_enough_episodes_finished(caplog):
    p = plan(CompletionCriteria("Jumper", "progress", min_lesson_length=10, threshold=0.1))
    totals = {"Jumper?team=0": (5, 5.0, 50)}
    assert p.update({"Jumper?team=0": 500}, totals) == (False, False)  # 5 of 10 episodes
    assert p.lessons == {"wall": 0}
    with caplog.at_level(logging.INFO, logger="driver.training.curriculum"):
        assert p.update({"Jumper?team=0": 500}, {"Jumper?team=0": (12, 12.0, 120)}) == (
            True,
            False,
        )
    assert p.lessons == {"wall": 1} and p.values() == {"wall": Constant(2.0)}
    assert "Parameter 'wall' is in lesson 'L1' and has value 'Float: value=2.0'." in caplog.text
    # the window starts over: 10 more episodes before the next lesson, however far progress is
    assert p.update({"Jumper?team=0": 900}, {"Jumper?team=0": (15, 15.0, 150)})[0] is False
    assert p.update({"Jumper?team=0": 900}, {"Jumper?team=0": (22, 22.0, 220)})[0] is True
    assert p.lessons == {"wall": 2}
    assert p.update({"Jumper?team=0": 1000}, {"Jumper?team=0": (99, 99.0, 990)})[0] is False


def test_a_behavior_not_seen_yet_keeps_the_lesson():
    p = plan(CompletionCriteria("Jumper", "progress", threshold=0.0))
    assert p.update({"Other?team=0": 900}, {"Other?team=0": (50, 0.0, 10)}) == (False, False)
    assert p.update({"Jumper?team=0": 1}, {}) == (True, False)


def test_reward_is_the_mean_of_the_latest_episodes_smoothed_as_mlagents():
    criteria = CompletionCriteria("B", "reward", min_lesson_length=4, threshold=0.5)
    p = plan(criteria)
    # 4 episodes of mean 0.6: smoothed 0.25 * 0 + 0.75 * 0.6 = 0.45, not above 0.5
    assert p.update({"B": 10}, {"B": (4, 2.4, 40)})[0] is False
    # the latest 4 (and more, as polls come whole) are all 1.0: 0.25 * 0.45 + 0.75 = 0.8625
    assert p.update({"B": 20}, {"B": (8, 6.4, 80)})[0] is True
    unsmoothed = plan(CompletionCriteria("B", "reward", 4, signal_smoothing=False, threshold=0.5))
    assert unsmoothed.update({"B": 10}, {"B": (4, 2.4, 40)})[0] is True


def test_teams_add_up_and_a_restarted_workers_totals_starting_over_count_nothing_twice():
    p = plan(CompletionCriteria("B", "reward", 6, signal_smoothing=False, threshold=0.9))
    p.update({"B?team=0": 1, "B?team=1": 1}, {"B?team=0": (2, 2.0, 2), "B?team=1": (2, 2.0, 2)})
    assert len(p.returns["B"]) == 4
    p.update({"B?team=0": 2}, {"B?team=0": (1, 1.0, 1)})  # a worker came back from zero
    assert len(p.returns["B"]) == 4
    assert p.update({"B?team=0": 3}, {"B?team=0": (4, 4.0, 4)})[0] is True  # 3 new: 7 >= 6


def test_the_return_window_keeps_the_latest_polls_that_hold_its_size():
    window = Returns(10)
    window.add(8, 0.0)
    window.add(8, 8.0)
    assert len(window) == 10 and window.mean() == 0.5  # 16 held: 8 alone are too few
    window.add(10, 20.0)
    assert len(window) == 10 and window.mean() == 2.0  # the latest 10 suffice: older go


def test_require_reset_is_reported_with_the_change():
    p = plan(CompletionCriteria("B", "progress", threshold=0.0, require_reset=True))
    assert p.update({"B": 1}, {}) == (True, True)


def test_unseeded_samplers_get_the_run_seed_plus_one_each_in_the_files_order():
    parameters = {
        "a": (Lesson("a", Uniform(0, 1, UNSEEDED)),),
        "b": (
            Lesson("b0", Gaussian(0, 1, 7), CompletionCriteria("B")),
            Lesson("b1", Uniform(0, 1, UNSEEDED), CompletionCriteria("B")),
            Lesson("b2", Constant(3.0)),
        ),
    }
    got = seeded(parameters, 100)
    assert got["a"][0].value == Uniform(0, 1, 100)
    assert got["b"][0].value == Gaussian(0, 1, 7)  # a seed of its own stays
    assert got["b"][1].value == Uniform(0, 1, 101)


@pytest.mark.parametrize(("saved", "expected"), [({"wall": 1}, 1), ({"wall": 9}, 2), (None, 0)])
def test_a_resumed_run_starts_in_the_lesson_its_checkpoint_names(saved, expected):
    p = plan(CompletionCriteria("B", "progress", threshold=0.5), lessons=saved)
    assert p.lessons == {"wall": expected}
    assert p.values() == {"wall": Constant(float(expected + 1))}
