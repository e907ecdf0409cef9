"""The learner's Ray host without Ray (``learners.host.remote.LearnerHost``): while its
process still loads torch it already takes segments, counts them for the driver's
summaries, and hands them to the learner once, in order."""

from __future__ import annotations

import os
import threading

import pytest

from batches.specs import spec_to_dict
from learners.host.remote import BUILD_NICENESS, LearnerHost
from learners.trainer_config.parse import parse_config
from testkit.segments import segment, vector_spec
from tests.learners.test_algorithms import as_segment
from tests.waiting import wait_for

BEHAVIOR = "A?team=0"


class HeldHost(LearnerHost):
    """A host whose learner is built only once the test lets it (its imports 'take' that long)."""

    def __init__(self, *args, **kwargs) -> None:
        self.gate = threading.Event()
        super().__init__(*args, **kwargs)

    def _build(self, *args) -> None:
        assert self.gate.wait(60)
        super()._build(*args)


def ppo_config(buffer_size: int):
    return parse_config(
        {
            "behaviors": {
                "A": {
                    "trainer_type": "ppo",
                    "hyperparameters": {"batch_size": 32, "buffer_size": buffer_size},
                }
            }
        }
    )


def piece(number: int, rows: int = 2, worker: str = "w"):
    return as_segment(
        segment(vector_spec(continuous=2), rows, 16, BEHAVIOR, seed=number), (worker, number)
    )


def test_segments_before_the_learner_is_built_are_counted_then_handed_over_once():
    host = HeldHost(ppo_config(buffer_size=100), None, 1, seed=0)
    try:
        # answered at once, with the first update's demand from the config (101 steps)
        assert host.submit([]) == (0, None)  # no behavior seen yet: no demand known
        assert host.submit([piece(1)]) == (0, 101 - 32)
        assert host.submit([piece(2), piece(1)]) == (0, 101 - 64)  # 1 again: a Ray retry
        progress = host.progress()
        assert progress["steps"] == {BEHAVIOR: 64} and progress["version"] == 0
        assert not progress["done"] and host.drain_reports() == []

        # the submission that fills the demand waits for the learner, then gets its answer
        answer: list[tuple[int, int | None]] = []
        filling = threading.Thread(target=lambda: answer.append(host.submit([piece(3, 3)])))
        filling.start()
        filling.join(0.5)
        assert filling.is_alive() and answer == []  # 112 steps in: it waits for the build
        assert host.progress()["steps"] == {BEHAVIOR: 112}
        host.gate.set()
        filling.join(120)
        assert answer == [(1, 101)]  # one update on the 112 steps; the next wants 101 more

        progress = host.progress()
        assert progress["steps"] == {BEHAVIOR: 112} and progress["version"] == 1
        assert progress["stats"].duplicate_steps == 32  # the retried delivery, taken once
        assert [b for b, _, _ in host.drain_reports()] == [BEHAVIOR]
        host.submit([piece(1)])  # a retry that comes after the handover: still taken once
        assert host.progress()["steps"] == {BEHAVIOR: 112}
        state = host.state_dict()
        assert state["step"] == 112 and state["version"] == 1
    finally:
        host.gate.set()


def test_off_policy_segments_wait_for_the_learner_without_a_demand():
    host = HeldHost(sac_config(), None, 1, seed=0)
    try:
        assert host.submit([piece(1)]) == (0, None)  # SAC: any amount, any time
        assert host.progress()["steps"] == {BEHAVIOR: 32}
        host.gate.set()
        assert host.submit([piece(2)])[1] is None  # built: both handed over, in order
        assert host.progress()["steps"] == {BEHAVIOR: 64}
    finally:
        host.gate.set()


@pytest.mark.parametrize("built", [False, True], ids=["loading", "built"])
def test_the_demand_never_passes_max_steps_and_ends_at_zero(built):
    """--max-steps 80: PPO asks for no more than the run still needs, SAC for any amount
    until then; once every behavior has its steps, both ask for nothing."""
    for config, first in ((ppo_config(buffer_size=100), 80 - 32), (sac_config(), None)):
        host = HeldHost(config, 80, 1, seed=0)
        try:
            if built:
                host.gate.set()
                host.prepare()
            assert host.submit([piece(1)]) == (0, first)
            host.gate.set()  # loading: the last submission waits for the build
            assert host.submit([piece(2), piece(3)])[1] == 0  # 96 steps of 80
        finally:
            host.gate.set()


def test_a_run_whose_steps_all_came_before_the_build_ends_only_once_trained():
    """A short SAC run (--max-steps 80, updates from 64 steps) whose workers bring every
    step while the learner still loads torch: the submission with the last steps waits
    for the learner, the run is not done before then, and the learner has updated on
    them when it is (in CI, such a run once ended with no update at all)."""
    config = parse_config(
        {"behaviors": {"A": {"trainer_type": "sac", "hyperparameters": {"batch_size": 64}}}}
    )
    host = HeldHost(config, 80, 1, seed=0)
    try:
        assert host.submit([piece(1), piece(2)]) == (0, None)  # 64 of 80: the run goes on
        answer: list[tuple[int, int | None]] = []
        ending = threading.Thread(target=lambda: answer.append(host.submit([piece(3)])))
        ending.start()
        ending.join(0.5)
        assert ending.is_alive() and answer == []  # 96 steps of 80: it waits for the build
        progress = host.progress()
        assert progress["steps"] == {BEHAVIOR: 96} and not progress["done"]
        host.gate.set()
        ending.join(120)
        assert answer and answer[0][1] == 0  # the run has its steps
        progress = host.progress()
        assert progress["done"] and progress["version"] >= 1
        reports = host.drain_reports()
        assert any(r["Policy/Gradient Steps"] > 0 for _, _, r in reports)
    finally:
        host.gate.set()


@pytest.mark.parametrize("built", [False, True], ids=["loading", "built"])
def test_a_behavior_met_before_its_rows_counts_towards_the_end_of_the_run(built):
    """As mlagents-learn makes a trainer when a behavior appears: a behavior the workers
    saw, whose rows have not come yet (WallJump's SmallWallJump), keeps the run going
    after the other has its steps, from the moment it is met (the learner's build may
    still take seconds then)."""
    config = parse_config({"behaviors": {"A": {"trainer_type": "sac"}, "B": {}}})
    specs = {name: spec_to_dict(vector_spec(continuous=2)) for name in (BEHAVIOR, "B")}
    host = HeldHost(config, 80, 1, seed=0)
    try:
        if built:
            host.gate.set()
            host.prepare()
        host.submit([piece(1), piece(2)])  # 64 steps of A's 80
        meeting = threading.Thread(target=host.meet, args=(specs,))
        meeting.start()  # while loading, it waits for the build
        wait_for(lambda: "B" in host.progress()["steps"], "B's steps in progress()", 60)
        progress = host.progress()
        assert progress["steps"] == {BEHAVIOR: 64, "B": 0} and not progress["done"]
        host.gate.set()
        meeting.join(120)
        host.submit([piece(3)])  # A has its steps, B none yet
        progress = host.progress()
        assert progress["steps"] == {BEHAVIOR: 96, "B": 0} and not progress["done"]
        host.submit([as_segment(segment(vector_spec(continuous=2), 3, 32, "B"), ("w", 4))])
        progress = host.progress()
        assert progress["steps"] == {BEHAVIOR: 96, "B": 96} and progress["done"]
    finally:
        host.gate.set()


def sac_config():
    return parse_config({"behaviors": {"A": {"trainer_type": "sac"}}})


def test_a_learner_that_fails_to_build_says_why_on_the_next_call():
    config = ppo_config(buffer_size=100)
    host = LearnerHost(config, None, 1, seed=0, device="cuda:7")  # no such device here
    with pytest.raises(RuntimeError, match="the learner failed to start: --device cuda:7") as err:
        host.state_dict()
    assert "\n" not in str(err.value)


def test_the_learner_is_built_at_a_lower_priority_than_the_rest_of_its_process():
    """The build's imports take CPU that the workers and their players need while they
    collect the first update's data; only the building thread yields it."""
    seen: list[int] = []

    class Recording(LearnerHost):
        def _build(self, *args) -> None:
            super()._build(*args)
            seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    host = Recording(ppo_config(buffer_size=100), None, 1, seed=0)
    host.prepare()  # waits for the build
    here = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    assert seen == [min(here + BUILD_NICENESS, 19)]
    assert os.getpriority(os.PRIO_PROCESS, 0) == here  # the process itself: unchanged
