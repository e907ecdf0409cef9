"""How a worker's failures are counted, without Ray running: one death is one failure,
whatever errors its restart shows on the way."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from ray.exceptions import ActorUnavailableError, RayTaskError

from rollout.service_config import RolloutError
from rollout.supervision import WorkerSupervision
from rollout.worker import WeightsLost


def supervisor(max_restarts: int) -> WorkerSupervision:
    s = WorkerSupervision()
    s.ledger = SimpleNamespace(ended=lambda index, reason: None)  # type: ignore[assignment]
    s.config = SimpleNamespace(max_worker_restarts=max_restarts, restart_wait_s=120.0)  # type: ignore[assignment]
    s.metrics = SimpleNamespace(worker_restarts=0)  # type: ignore[assignment]
    s.membership = None
    s._idle, s._failures, s._restarting, s._retry_at = set(), [0], {}, {}
    s._worker_version = [20]
    return s


def weights_lost() -> RayTaskError:
    return RayTaskError("collect", "traceback", WeightsLost("worker has version 0, sent 20"))


def test_a_restart_seen_as_unavailable_then_weights_lost_is_one_failure():
    s = supervisor(max_restarts=1)
    s._collect_failed(0, None, ActorUnavailableError("restarting", None))
    s._collect_failed(0, None, ActorUnavailableError("restarting", None))  # retried meanwhile
    s._collect_failed(0, None, weights_lost())  # the new incarnation: resend the weights
    assert s.metrics.worker_restarts == 1 and s._failures == [1]
    assert 0 in s._idle and s._worker_version == [0]  # weights go out with the next collect


def test_a_restart_while_idle_is_seen_only_as_weights_lost_and_counts():
    s = supervisor(max_restarts=1)
    s._collect_failed(0, None, weights_lost())
    assert s.metrics.worker_restarts == 1
    with pytest.raises(RolloutError, match="worker 0 failed 2 times in a row"):
        s._collect_failed(0, None, weights_lost())  # a second death, not seen otherwise
