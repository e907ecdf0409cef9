"""The learner as a Ray actor (``learners.host.remote.learner_actor``): the driver's status
calls answer while an update runs."""

from __future__ import annotations

import pytest

from learners.host.remote import learner_actor
from learners.trainer_config.parse import parse_config
from testkit.segments import segment, vector_spec
from tests.waiting import wait_for

pytestmark = pytest.mark.integration


def test_progress_answers_while_an_update_runs(ray_session):
    """The summary at a step count comes before the update that follows it, as in
    mlagents-learn, and the driver never waits seconds on the learner for its table."""
    config = parse_config(
        {
            "behaviors": {
                "A": {
                    "trainer_type": "ppo",
                    "hyperparameters": {"batch_size": 64, "buffer_size": 4096, "num_epoch": 60},
                }
            }
        }
    )
    learner = learner_actor(config)
    spec = vector_spec(continuous=2)
    try:
        data = [segment(spec, 64, 65, "A?team=0")]  # 4160 steps: more than the buffer
        updating = learner.submit.remote(data)  # 60 epochs of 64 minibatches: seconds
        progress: dict = {}

        def counted() -> bool:  # the submit has counted its steps
            progress.update(ray_session.get(learner.progress.remote(), timeout=60))
            return bool(progress["steps"])

        wait_for(counted, "the submit's steps in progress()", 240)
        ready, _ = ray_session.wait([updating], timeout=0)
        assert ready == [], f"progress waited for the update: {progress}"
        assert progress["steps"] == {"A?team=0": 4160} and progress["version"] == 0, progress
        assert ray_session.get(updating, timeout=300)[0] == 1
        assert ray_session.get(learner.progress.remote())["version"] == 1
        assert [b for b, _, _ in ray_session.get(learner.drain_reports.remote())] == ["A?team=0"]
    finally:
        ray_session.kill(learner)
