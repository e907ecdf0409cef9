"""The learner keeper: a learner that ran out of memory is not brought back to fill the
same buffer again (no Ray); one lost before the first checkpoint comes back with the
networks the run started from (a Ray actor)."""

from __future__ import annotations

import pytest

from driver.training.learner_keeper import LearnerKeeper
from rollout.serving.config import RolloutError


def test_a_learner_out_of_memory_ends_the_run_instead_of_refilling_the_same_buffer(tmp_path):
    keeper = LearnerKeeper(None, lambda: pytest.fail("no new learner"), tmp_path, 3)
    with pytest.raises(RolloutError) as raised:
        keeper.restore(None, "ran out of memory on node 10.0.0.5 (30.12 GB of 31.20 GB in use)")  # type: ignore[arg-type]
    assert "lower the behaviors' buffer_size" in str(raised.value)
    assert "last checkpoint stays" in str(raised.value)


def test_a_learner_lost_before_the_first_checkpoint_comes_back_with_the_runs_first_networks(
    ray_session, tmp_path
):
    """``--initialize-from``: the learner the keeper starts anew holds the other run's
    networks, as the run's first did, not the factory's (with ``--inference`` no checkpoint
    is ever written, so every restart comes back this way)."""
    from types import SimpleNamespace

    import numpy as np

    from driver.options import TrainOptions
    from driver.system import start_learner
    from learners.host.learner import CentralLearner
    from learners.trainer_config.parse import parse_config
    from testkit.segments import segment, vector_spec

    config = parse_config(
        {"behaviors": {"A": {"hyperparameters": {"batch_size": 8, "buffer_size": 16}}}}
    )
    source = CentralLearner(config, seed=1)
    source.submit([segment(vector_spec(continuous=2), 2, 10, "A?team=0", seed=n) for n in range(2)])
    initial = source.state_dict()
    start = lambda: start_learner(TrainOptions(), config, "cpu", {}, initial)  # noqa: E731
    keeper = LearnerKeeper(start(), start, tmp_path, 3)
    service = SimpleNamespace(
        metrics=SimpleNamespace(learner_restarts=0), version=1, replace_learner=lambda _: None
    )
    restored = keeper.restore(service, "the actor died")  # type: ignore[arg-type]
    version, weights = ray_session.get(restored.weights.remote())
    assert version == 2  # past every version the lost one published
    for key, value in source.weights()[1]["A?team=0"].items():
        np.testing.assert_array_equal(weights["A?team=0"][key], value, err_msg=key)
    ray_session.kill(restored)
