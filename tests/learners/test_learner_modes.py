"""The central learner's other ways to start and run, as mlagents-learn's options ask:
from another run's networks (``--initialize-from``), and without training
(``--inference``)."""

from __future__ import annotations

import numpy as np

from learners.host.learner import CentralLearner
from learners.trainer_config.parse import parse_config
from testkit.segments import segment, vector_spec

CONFIG = parse_config(
    {"behaviors": {"A": {"hyperparameters": {"batch_size": 32, "buffer_size": 64}}}}
)
SPEC = vector_spec(continuous=2)


def trained() -> CentralLearner:
    learner = CentralLearner(CONFIG, seed=1)
    learner.submit([segment(SPEC, 5, 16, "A?team=0", seed=n) for n in range(2)])
    assert learner.version > 0  # it updated
    return learner


def test_initialize_from_takes_the_networks_and_nothing_else():
    source = trained()
    fresh = CentralLearner(CONFIG, seed=2)
    fresh.initialize(source.state_dict())
    # a version of their own, newer than the factory's that workers start from
    assert fresh.version == 1 and fresh.progress()["steps"] == {"A?team=0": 0}
    assert fresh.behaviors["A?team=0"].updates == []
    ours, theirs = fresh.weights()[1]["A?team=0"], source.weights()[1]["A?team=0"]
    for key, value in theirs.items():
        np.testing.assert_array_equal(ours[key], value, err_msg=key)
    fresh.submit([segment(SPEC, 5, 16, "A?team=0", seed=9)])
    assert fresh.version == 2  # and it trains on from there


def test_inference_counts_steps_and_trains_on_none():
    learner = CentralLearner(CONFIG, max_steps=300, inference=True)
    before = None
    for n in range(3):
        version, wanted = learner.submit([segment(SPEC, 5, 16, "A?team=0", seed=n)])
        assert (version, wanted) == (0, None)  # no update, and any amount until the end
        weights = learner.weights()[1]["A?team=0"]
        if before is not None:
            for key, value in before.items():
                np.testing.assert_array_equal(weights[key], value, err_msg=key)
        before = weights
    assert learner.progress()["steps"] == {"A?team=0": 240}
    assert learner.submit([segment(SPEC, 5, 16, "A?team=0")]) == (0, 0)  # 320 of 300: done
