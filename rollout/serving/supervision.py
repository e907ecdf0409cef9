"""What the rollout service does when a worker's collect fails, and as the cluster changes:

- a worker Ray is restarting (``--workers N``): retried until it is back, counted once;
- a worker that died: with ``--workers N`` Ray restarts it in place, and one that keeps
  dying ends the run; with ``--workers auto`` (elastic) it is retired, having left with its
  node or alone, and the cluster's room decides its successor (``rollout/serving/membership.py``);
- the learner died under the collect (its weights were the collect's argument);
- a cause that no restart cures (Unity's restart budget spent): the run ends, naming it;
- a worker Ray is restarting when the run stops: closed once it is back.

A mixin of ``RolloutService``: the state it reads and writes is the service's.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

import ray
from ray.exceptions import ActorUnavailableError, ObjectLostError, RayActorError, RayTaskError

from rollout.collecting.ledger import WORKER_DEATH
from rollout.collecting.worker import WeightsLost
from rollout.serving.config import LearnerDied, RolloutError, last_line

if TYPE_CHECKING:
    from rollout.collecting.ledger import Ledger
    from rollout.serving.config import ServiceConfig
    from rollout.serving.membership import Membership
    from rollout.serving.metrics import ServiceMetrics

log = logging.getLogger("rollout.serving.service")

RETRY_PAUSE_S = 0.5  # between calls sent to a worker that Ray is restarting
CLOSE_WAIT_S = 60.0  # for all workers' closes at the end of a run


class WorkerSupervision:
    config: ServiceConfig
    learner: Any
    workers: list[Any]
    ledger: Ledger
    metrics: ServiceMetrics
    membership: Membership | None
    _idle: set[int]
    _failures: list[int]
    _worker_version: list[int]
    _restarting: dict[int, float]
    _counted_unseen: set[int]
    _retry_at: dict[int, float]
    _stale: set[Any]
    _dead_learners: set[str]

    def _make_worker(self, index: int) -> Any: ...

    def live(self) -> list[int]: ...

    def _collect_failed(self, index: int, ref: Any, error: Exception) -> int:
        """A collect raised ``error`` instead of returning segments; returns 0 (routed)."""
        if (learner := self._dead_learner(error)) is not None:  # the weights it was sent
            self._stale.discard(ref)
            self._idle.add(index)  # the worker never ran it: it acts on with what it had
            if learner in self._dead_learners:
                return 0  # one that was replaced already
            raise LearnerDied(last_line(error)) from None
        if isinstance(error, RayTaskError):  # collect raised: e.g. Unity's budget is spent
            cause = getattr(error, "cause", None) or error
            if isinstance(cause, WeightsLost):  # restarted: resend the weights
                if index not in self._restarting:  # a death not seen yet (it was idle)
                    self._count_failure(index, error)
                    self._counted_unseen.add(index)
                self._worker_version[index] = 0  # also when a retry had sent them before
                self._idle.add(index)
                return 0
            raise RolloutError(f"worker {index}: {last_line(cause)}") from None
        if isinstance(error, ActorUnavailableError):  # died, and Ray is bringing it back
            now = time.perf_counter()
            if index not in self._restarting:
                self.ledger.ended(index, WORKER_DEATH)
                self._count_failure(index, error)
                self._restarting[index] = now
            elif now - self._restarting[index] > self.config.restart_wait_s:
                raise RolloutError(
                    f"worker {index} did not come back within {self.config.restart_wait_s:.0f} s "
                    f"of its restart; last: {last_line(error)}"
                ) from None
            self._worker_version[index] = 0  # the weights this collect carried never arrived
            self._retry_at[index] = now + RETRY_PAUSE_S
            return 0
        if not isinstance(error, RayActorError | ObjectLostError):  # lost: with its node
            raise error
        self._stale.discard(ref)
        if self.membership is not None:
            self._retire(index, error)
            return 0
        self.ledger.ended(index, WORKER_DEATH)
        self._count_failure(index, error)
        self._idle.add(index)
        return 0

    def _dead_learner(self, error: Exception) -> str | None:
        """The actor id of the learner (this one or a replaced one) whose death ``error`` is,
        or None. A collect sent the weights a learner had not finished publishing fails on
        that argument as ``RayTaskError(ActorDiedError)``: a task error and its death at once."""
        died = getattr(error, "actor_id", None) if isinstance(error, RayActorError) else None
        if died is not None and (
            died == self.learner._actor_id.hex() or died in self._dead_learners
        ):
            return died
        return None

    def _grow(self) -> None:
        """Elastic: start a worker for each slot the cluster gained (first weights with
        its first collect, as after a restart)."""
        assert self.membership is not None
        for _ in range(self.membership.missing(self.live())):
            index = len(self.workers)
            self.workers.append(self._make_worker(index))
            self._worker_version.append(0)
            self._failures.append(0)
            self._idle.add(index)
            self.membership.added += 1
            log.info("worker %d joins: %d live", index, len(self.live()))

    def _retire(self, index: int, error: Exception) -> None:
        """Elastic: a worker died (with its node, or alone): its rows in progress are
        dropped, and the cluster's room, not a restart in place, decides its successor."""
        assert self.membership is not None
        if index in self.membership.retired:
            return
        self.ledger.ended(index, WORKER_DEATH)
        self._idle.discard(index)
        self._retry_at.pop(index, None)
        ray.kill(self.workers[index], no_restart=True)
        if not self.membership.retire(index):
            raise RolloutError(
                f"{self.membership.barren} workers in a row died before their first collect; "
                f"last: {last_line(error)}"
            )
        log.warning("worker %d left (%s): %d live", index, last_line(error), len(self.live()))

    def _take_counted(self, index: int) -> bool:
        """Whether this worker's unseen restart was counted already (through WeightsLost)."""
        counted = index in self._counted_unseen
        self._counted_unseen.discard(index)
        return counted

    def _count_failure(self, index: int, error: Exception) -> None:
        """A worker died: count it, end the run if it keeps dying, else let Ray restart it."""
        self.metrics.worker_restarts += 1
        self._failures[index] += 1
        if self._failures[index] > self.config.max_worker_restarts:
            raise RolloutError(
                f"worker {index} failed {self._failures[index]} times in a row; "
                f"last: {last_line(error)}"
            ) from None
        log.warning("worker %d died (%s); Ray restarts it", index, error)
        self._worker_version[index] = 0  # a restarted worker needs the weights again

    def _close(self, indices: list[int]) -> dict[int, Any]:
        """Each worker's close: its last ``Collected``, or the error it raised. One that Ray
        is restarting is asked again until it is back: killed in the middle of its start,
        its new process once outlived the kill and Ray itself, holding its port."""
        deadline = time.monotonic() + CLOSE_WAIT_S
        calls = {self.workers[i].close.remote(): i for i in indices}
        closed: dict[int, Any] = {}
        while calls:
            left = deadline - time.monotonic()
            ready, _ = ray.wait(list(calls), num_returns=1, timeout=max(left, 0.0))
            if not ready:
                break
            index = calls.pop(ready[0])
            try:
                closed[index] = ray.get(ready[0])
            except ActorUnavailableError as error:
                if deadline - time.monotonic() < RETRY_PAUSE_S:
                    closed[index] = error
                    continue
                time.sleep(RETRY_PAUSE_S)
                calls[self.workers[index].close.remote()] = index
            except Exception as error:  # dead: its launch guard already took the player
                closed[index] = error
        for index in calls.values():
            closed[index] = TimeoutError(f"no answer within {CLOSE_WAIT_S:.0f} s")
        return closed
