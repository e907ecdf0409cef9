"""The learner keeper without Ray: a learner that ran out of memory is not brought back
to fill the same buffer again."""

from __future__ import annotations

import pytest

from driver.learner_keeper import LearnerKeeper
from rollout.service_config import RolloutError


def test_a_learner_out_of_memory_ends_the_run_instead_of_refilling_the_same_buffer(tmp_path):
    keeper = LearnerKeeper(None, lambda: pytest.fail("no new learner"), tmp_path, 3)
    with pytest.raises(RolloutError) as raised:
        keeper.restore(None, "ran out of memory on node 10.0.0.5 (30.12 GB of 31.20 GB in use)")  # type: ignore[arg-type]
    assert "lower the behaviors' buffer_size" in str(raised.value)
    assert "last checkpoint stays" in str(raised.value)
