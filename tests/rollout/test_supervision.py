"""How a worker's failures are counted, without Ray running: one death is one failure,
whatever errors its restart shows on the way; a learner's death is the learner's, also when
a collect shows it as a task error."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from ray.exceptions import ActorDiedError, ActorUnavailableError, RayTaskError

from rollout.collecting.worker import WeightsLost
from rollout.serving.config import LearnerDied, RolloutError, last_line
from rollout.serving.supervision import WorkerSupervision


def supervisor(max_restarts: int) -> WorkerSupervision:
    s = WorkerSupervision()
    s.ledger = SimpleNamespace(ended=lambda index, reason: None)  # type: ignore[assignment]
    s.config = SimpleNamespace(max_worker_restarts=max_restarts, restart_wait_s=120.0)  # type: ignore[assignment]
    s.metrics = SimpleNamespace(worker_restarts=0)  # type: ignore[assignment]
    s.membership = None
    s._idle, s._failures, s._restarting, s._retry_at = set(), [0], {}, {}
    s._counted_unseen = set()
    s._worker_version = [20]
    s.learner = SimpleNamespace(_actor_id=bytes.fromhex("1e"))
    s._dead_learners, s._stale = {"de"}, set()
    return s


def weights_lost() -> RayTaskError:
    return RayTaskError("collect", "traceback", WeightsLost("worker has version 0, sent 20"))


def test_a_restart_seen_as_unavailable_then_weights_lost_is_one_failure():
    """Each retry is a collect that carried the weights (the service's ``_issue`` marks the
    worker as having them) and never arrived: the new incarnation must get them again, or it
    answers every later collect with WeightsLost (seen in CI under load: a run that stalled)."""
    s = supervisor(max_restarts=1)
    s._collect_failed(0, None, ActorUnavailableError("restarting", None))
    s._worker_version[0] = 20  # the retry carried the weights
    s._collect_failed(0, None, ActorUnavailableError("restarting", None))
    assert s._worker_version == [0]
    s._worker_version[0] = 20  # the next retry too
    s._collect_failed(0, None, weights_lost())  # the new incarnation: resend the weights
    assert s.metrics.worker_restarts == 1 and s._failures == [1]
    assert 0 in s._idle and s._worker_version == [0]  # weights go out with the next collect


def test_a_restart_while_idle_is_seen_only_as_weights_lost_and_counts():
    s = supervisor(max_restarts=1)
    s._collect_failed(0, None, weights_lost())
    assert s.metrics.worker_restarts == 1
    with pytest.raises(RolloutError, match="worker 0 failed 2 times in a row"):
        s._collect_failed(0, None, weights_lost())  # a second death, not seen otherwise


def died_under_the_argument(learner: str) -> RayTaskError:
    """What Ray raised (ray 2.60, tried) for a collect sent the weights ``learner.weights``
    had not yet returned when that learner was SIGKILLed."""
    death = ActorDiedError()
    death.actor_id = learner
    return RayTaskError("collect", "traceback", death, actor_id="0a").as_instanceof_cause()


def test_a_collect_failed_on_a_dying_learners_weights_is_the_learners_death():
    s = supervisor(max_restarts=1)
    with pytest.raises(LearnerDied):
        s._collect_failed(0, None, died_under_the_argument("1e"))
    assert s.metrics.worker_restarts == 0 and 0 in s._idle  # not the worker's failure
    assert s._collect_failed(0, None, died_under_the_argument("de")) == 0  # replaced already


def test_a_collect_that_raised_in_the_worker_ends_the_run_naming_it():
    s = supervisor(max_restarts=1)
    error = RayTaskError("collect", "traceback", RuntimeError("restart budget spent"))
    with pytest.raises(RolloutError, match=r"worker 0: .*restart budget spent"):
        s._collect_failed(0, None, error)


# Ray's memory monitor's messages: 2.60's raylet, and the form before 2.40 (Ray's docs)
RAY_260_OOM = (
    "The actor died unexpectedly before finishing this task.\n\tclass_name: LearnerHost\n"
    "The actor is dead because its worker process has died. Worker exit type: "
    "USER_ERROR Worker exit detail: 1 worker(s) were killed due to the node running low "
    "on memory. Memory on the node (IP: 10.0.0.5, ID: 3a4b60) was 30.12GB used / 31.20GB "
    "limit (0.965385)\nTop 10 memory users:\nPID\tMEM(GB)\tCOMMAND\n411\t19.60\tray::LearnerHost"
)
RAY_OLD_OOM = (
    "Task was killed due to the node running low on memory.\nMemory on the node (IP: "
    "172.17.0.2, ID: 3a4b60) where the task was running was 32.53GB / 33.28GB (0.977449), "
    "which exceeds the memory usage threshold of 0.969955.\nConsider provisioning more memory"
)


@pytest.mark.parametrize(
    ("text", "where"),
    [
        (RAY_260_OOM, "10.0.0.5 (30.12 GB of 31.20 GB"),
        (RAY_OLD_OOM, "172.17.0.2 (32.53 GB of 33.28 GB"),
    ],
)
def test_an_out_of_memory_kill_is_one_line_naming_the_node(text, where):
    line = last_line(RuntimeError(text))
    assert line == f"ran out of memory on node {where} in use): Ray's memory monitor killed it"
