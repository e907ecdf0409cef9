"""An on-policy update takes the trajectories up to the one that tips its buffer over (and
those finished in the same exchange), as mlagents-learn's does, however many trajectories
the segment that brought it holds; the rest wait for the next update."""

from __future__ import annotations

import torch

from batches import keys
from learners.algorithms.update_cut import update_cut
from learners.host.learner import CentralLearner
from learners.trainer_config.parse import parse_config
from testkit.segments import segment, vector_spec

SPEC = vector_spec(branches=(3,))
CONFIG = parse_config(
    {"behaviors": {"A": {"hyperparameters": {"batch_size": 32, "buffer_size": 100}}}}
)


def test_the_cut_falls_after_the_trajectory_that_brings_the_wanted_steps():
    ten = segment(SPEC, rows=10, steps=30)  # trajectories end at steps 30, 60, ... 300
    assert update_cut(ten, 101) == 120  # 90 are not enough; the fourth brings 120
    assert update_cut(ten, 90) == 90
    assert update_cut(ten, 1) == 30
    assert update_cut(ten, 300) == update_cut(ten, 1000) == 300


def test_trajectories_finished_in_the_same_exchange_go_together():
    ten = segment(SPEC, rows=10, steps=30)
    ten[keys.ENV_STEPS] = torch.tensor([3] * 90 + [7] * 90 + [9] * 120)
    assert update_cut(ten, 101) == 180  # the fourth ended with the fifth and sixth
    assert update_cut(ten, 31) == 90  # the first three, one exchange
    assert update_cut(ten, 181) == 300


def test_one_large_segment_gives_updates_of_mlagents_size_and_keeps_the_rest():
    learner = CentralLearner(CONFIG, seed=0)
    version, wanted = learner.submit([segment(SPEC, rows=10, steps=30, behavior="A?team=0")])
    sizes = [report["Policy/Samples"] for _, _, report in learner.drain_reports()]
    assert version == 2 and sizes == [120, 120]  # not one update of all 300
    assert wanted == 101 - 60  # the last two trajectories wait for the next update
    assert learner.progress()["steps"] == {"A?team=0": 300}
    learner.submit([segment(SPEC, rows=2, steps=30, behavior="A?team=0", seed=1)])
    assert [r["Policy/Samples"] for _, _, r in learner.drain_reports()] == [120]


def test_no_update_once_the_behavior_has_its_steps():
    learner = CentralLearner(CONFIG, max_steps=100, seed=0)
    learner.submit([segment(SPEC, rows=10, steps=30, behavior="A?team=0")])
    # the delivery's first 120 steps cross the budget and update; the next 120 do not
    assert [r["Policy/Samples"] for _, _, r in learner.drain_reports()] == [120]
    assert learner.progress()["done"]
