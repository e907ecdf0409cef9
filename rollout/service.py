"""The rollout service: starts N workers, routes their segments to the learner, brings
newer weights back, supervises, aggregates metrics, and stops everything cleanly.

Data flow (all ObjectRefs; the driver never touches segment data)::

    worker.collect(version, weights)  ->  segments ref  ->  learner.submit(segments)
          ^                                                         |
          +------ weights ref (one ray.put per version) <-----------+

Back-pressure: each worker has at most ``collects_per_worker`` collect calls in flight,
and at most ``learner_in_flight`` submissions wait at the learner; while the learner is
behind, no new collect is issued. Nothing queues without bound.

Demand: ``submit`` also answers how many more steps the learner wants before its next
update of an on-policy behavior (PPO), or None. While steps already in flight cover that
demand, idle workers wait for the new weights instead of acting with old ones: each
update then trains on data of the policy it improves, as in mlagents-learn's synchronous
loop. Off-policy and V-trace learners answer None and keep every worker busy.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import ray
from ray.exceptions import ActorUnavailableError, RayActorError, RayTaskError

from rollout import keys
from rollout.collector import ActorFactory
from rollout.ledger import (
    LEARNER_RESTART,
    SHUTDOWN,
    WORKER_DEATH,
    Ledger,
    steps_of,
)
from rollout.ports import PortRange
from rollout.service_metrics import ServiceMetrics, WorkerReports
from rollout.unity import UnityConfig
from rollout.worker import RolloutWorker, WeightsLost

log = logging.getLogger(__name__)


RETRY_PAUSE_S = 0.5  # between collects sent to a worker that Ray is restarting
REPORT_WAIT_S = 2.0  # at the end of ``run``: for metrics of workers between collects


class RolloutError(RuntimeError):
    """Collection cannot go on (a worker keeps failing); the message names the cause."""


class LearnerDied(RuntimeError):
    """The learner actor is gone (OOM, a GPU error, SIGKILL). The driver brings a new one
    back from the last checkpoint and hands it to ``replace_learner``; the workers keep
    their Unity instances and weights meanwhile."""


def last_line(error: Exception) -> str:
    text = str(error).strip()
    return text.splitlines()[-1] if text else type(error).__name__


@dataclass(frozen=True)
class ServiceConfig:
    unity: UnityConfig
    num_workers: int = 2
    horizon: int = 64  # steps after which a row is cut (ML-Agents' time_horizon)
    min_steps: int = 512  # steps of finished rows a collect call waits for (no demand)
    max_collect_s: float = 0.5  # ... or this long, so data and metrics keep flowing
    collects_per_worker: int = 1
    learner_in_flight: int = 2
    worker_cpus: float = 1.0
    # Wait for the learner's weights before the first collect (a resumed learner). A fresh
    # learner holds the factory's initial weights, which each worker builds for itself:
    # collection then starts while the learner's process is still starting.
    await_learner_weights: bool = True
    max_worker_restarts: int = 3
    restart_wait_s: float = 120.0  # how long a worker may take to come back after a death
    port_range: PortRange | None = None
    registry_dir: str | None = None


class RolloutService:
    def __init__(
        self,
        config: ServiceConfig,
        actor_factory: ActorFactory,
        learner: ray.actor.ActorHandle,
    ) -> None:
        self.config = config
        self.actor_factory = actor_factory
        self.learner = learner
        self.workers: list[ray.actor.ActorHandle] = []
        self.metrics = ServiceMetrics()
        self._version = 0
        self._weights_ref: ray.ObjectRef | None = None
        self._worker_version: list[int] = []
        self._collects: dict[ray.ObjectRef, tuple[int, int]] = {}  # -> (worker, min steps)
        self._idle: set[int] = set()  # workers that can take another collect
        self._submits: list[ray.ObjectRef] = []
        # per submission: (worker, incarnation, steps per behavior), for demand and ledger
        self._books: dict[ray.ObjectRef, tuple[int, str, dict[str, int]]] = {}
        self.ledger = Ledger()
        self._wanted: int | None = None  # the learner's last answer: steps before its update
        self._failures: list[int] = []  # consecutive failed collects per worker
        self._restarting: dict[int, float] = {}  # worker index -> when it went away
        self._retry_at: dict[int, float] = {}  # worker index -> when to ask it again
        self._reports = WorkerReports()
        self._stale: set[ray.ObjectRef] = set()  # collects acted by a dead learner's weights
        self._dead_learners: set[str] = set()  # actor ids of learners replaced
        self._started = 0.0

    # --- lifecycle ----------------------------------------------------------------------

    def _make_worker(self, index: int) -> ray.actor.ActorHandle:
        config = self.config
        return RolloutWorker.options(
            num_cpus=config.worker_cpus,
            max_restarts=config.max_worker_restarts,
            name=None,
        ).remote(
            index,
            config.unity,
            self.actor_factory,
            config.horizon,
            config.port_range,
            config.registry_dir,
        )

    def start(self) -> None:
        self._started = time.perf_counter()
        # Workers first: their processes and Unity players start while the learner's does.
        self.workers = [self._make_worker(i) for i in range(self.config.num_workers)]
        first = self.learner.submit.remote([])  # (version, demand), as every submit answers
        if self.config.await_learner_weights:
            self._weights_ref = self.learner.weights.remote()
            self._version = int(ray.get(self._weights_ref)[0])
            self._wanted = ray.get(first)[1]
        else:  # answered whenever the learner is up, like any submission
            self._version, self._wanted = 0, None
            self._submits.append(first)
        self._worker_version = [0] * len(self.workers)
        self._failures = [0] * len(self.workers)
        self._restarting.clear()
        self._retry_at.clear()
        self._reports = WorkerReports()
        self._idle = set(range(len(self.workers)))
        for index in range(len(self.workers)):
            for _ in range(self.config.collects_per_worker - 1):
                self._issue(index)
        self._pump()

    def stop(self) -> None:
        """Close every worker's Unity instance, then end the actors."""
        closing = [w.close.remote() for w in self.workers]
        ray.wait(closing, num_returns=len(closing), timeout=60)
        self._drain_submits(block=False, timeout=10.0, lost=SHUTDOWN)
        finished, _ = ray.wait(list(self._collects), num_returns=len(self._collects), timeout=0)
        for ref in finished:  # read, so that Ray does not report their errors as unhandled
            with contextlib.suppress(Exception):
                collected = ray.get(ref)
                index = self._collects[ref][0]
                self.ledger.arrived(index, collected)
                self.ledger.book(index, collected.incarnation, steps_of(collected), SHUTDOWN)
        for index, call in enumerate(closing):
            try:
                self.ledger.ended(index, SHUTDOWN, ray.get(call, timeout=0))
            except Exception as error:  # dead: its launch guard already took the player
                log.warning("while closing worker %d: %s", index, last_line(error))
                dead = isinstance(error, RayActorError)
                self.ledger.ended(index, WORKER_DEATH if dead else SHUTDOWN)
        self.metrics.dropped_by_reason = self.ledger.dropped_by_reason()
        for worker in self.workers:
            ray.kill(worker, no_restart=True)
        self.workers = []
        self._reports.calls.clear()
        self._collects.clear()
        self._submits.clear()
        self._books.clear()
        self._idle.clear()

    def __enter__(self) -> RolloutService:
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    # --- routing ------------------------------------------------------------------------

    def _issue(self, index: int, min_steps: int | None = None) -> None:
        weights = self._weights_ref if self._worker_version[index] < self._version else None
        steps = min_steps or self.config.min_steps
        ref = self.workers[index].collect.remote(
            self._version, weights, steps, self.config.max_collect_s
        )
        self._worker_version[index] = self._version
        self._collects[ref] = (index, steps)

    def _pump(self) -> None:
        """Give idle workers a collect, as far as the learner's demand reaches."""
        idle = [i for i in self._idle if i not in self._retry_at]
        if not idle:
            return
        if self._wanted is None:
            for index in idle:
                self._issue(index)
            self._idle.difference_update(idle)
            return
        coming = sum(steps for _, steps in self._collects.values())
        coming += sum(sum(steps.values()) for _, _, steps in self._books.values())
        missing = self._wanted - coming
        if missing <= 0:
            return  # in flight already fills the next update: wait for its weights
        share = math.ceil(missing / len(idle))
        for index in idle:
            self._issue(index, share)
        self._idle.difference_update(idle)

    def step(self, timeout: float = 60.0) -> int:
        """Route one finished collect to the learner; returns the segments routed."""
        self._drain_submits(block=len(self._submits) >= self.config.learner_in_flight)
        now = time.perf_counter()
        for index in [i for i, at in self._retry_at.items() if at <= now]:
            del self._retry_at[index]
            self._idle.add(index)
        self._pump()
        if self._retry_at:  # come back in time for the next retry
            timeout = max(0.0, min(timeout, min(self._retry_at.values()) - now))
        if not self._collects:
            if self._submits:  # waiting on the learner: its answer opens new collects
                self._drain_submits(block=True, timeout=timeout)
            else:
                time.sleep(timeout)
            return 0
        ready, _ = ray.wait(list(self._collects), num_returns=1, timeout=timeout)
        if not ready:
            return 0
        ref = ready[0]
        index, _ = self._collects.pop(ref)
        try:
            segments = ray.get(ref)
            self.ledger.arrived(index, segments)
            if ref in self._stale:  # weights the restored learner never had: drop
                self._stale.discard(ref)
                self.ledger.book(index, segments.incarnation, steps_of(segments), LEARNER_RESTART)
                segments = []
        except RayTaskError as error:  # collect raised: e.g. Unity's restart budget is spent
            cause = getattr(error, "cause", None) or error
            if isinstance(cause, WeightsLost):  # restarted while idle: resend the weights
                self._count_failure(index, error)
                self._idle.add(index)
                return 0
            raise RolloutError(f"worker {index}: {last_line(cause)}") from None
        except ActorUnavailableError as error:  # died, and Ray is bringing it back
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
            self._retry_at[index] = now + RETRY_PAUSE_S
            return 0
        except RayActorError as error:
            self._stale.discard(ref)
            died = getattr(error, "actor_id", None)
            if died == self.learner._actor_id.hex() or died in self._dead_learners:
                self._idle.add(index)  # the weights it was sent died with a learner
                if died in self._dead_learners:
                    return 0  # one that was replaced already
                raise LearnerDied(last_line(error)) from None
            self.ledger.ended(index, WORKER_DEATH)
            self._count_failure(index, error)
            self._idle.add(index)
            return 0
        self._failures[index] = 0
        self._restarting.pop(index, None)
        self._idle.add(index)
        if segments:
            submit = self.learner.submit.remote(ref)
            self._submits.append(submit)
            self._books[submit] = (index, segments.incarnation, steps_of(segments))
            self._observe(segments)
        return len(segments)

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

    def _drain_submits(
        self, block: bool, timeout: float | None = None, lost: str | None = None
    ) -> None:
        """Take the learner's answers; ``lost``: the reason to book what does not come
        back within ``timeout`` (at shutdown), instead of waiting for it."""
        if not self._submits:
            return
        done, self._submits = ray.wait(
            self._submits,
            num_returns=1 if block else len(self._submits),
            timeout=timeout if (block or lost) else 0,
        )
        try:
            answers = ray.get(done)
        except RayActorError as error:
            if lost is None:
                raise LearnerDied(last_line(error)) from None
            self._submits += done  # booked as lost below
            done, answers = [], []
        for ref in self._submits if lost else []:
            if ref in self._books:
                self.ledger.book(*self._books.pop(ref), lost)
        for ref, (version, wanted) in zip(done, answers, strict=True):
            if ref in self._books:
                self.ledger.book(*self._books.pop(ref), "delivered")
            self._wanted = wanted
            if version > self._version:
                self._version = version
                self._weights_ref = self.learner.weights.remote()

    def replace_learner(self, learner: ray.actor.ActorHandle) -> None:
        """Route to a learner restored after the last one died. What was in flight to the
        dead one is lost, and collects now running act with weights the restored learner
        never had: their steps are dropped (the ledger's ``learner restart``). The restored
        learner's version is above any the dead one published (the driver sets it), so
        every worker takes its weights with its next collect."""
        self.metrics.learner_restarts += 1
        self._dead_learners.add(self.learner._actor_id.hex())
        for book in self._books.values():
            self.ledger.book(*book, LEARNER_RESTART)
        self._books.clear()
        self._submits.clear()
        self._stale = set(self._collects)
        self.learner = learner
        self._weights_ref = learner.weights.remote()
        self._version = int(ray.get(self._weights_ref)[0])
        self._wanted = ray.get(learner.submit.remote([]))[1]

    @property
    def version(self) -> int:
        """The newest weights version the service has seen published."""
        return self._version

    def _observe(self, segments: list) -> None:
        for segment in segments:
            self.metrics.segments += 1
            lag = self._version - segment.data[keys.POLICY_VERSION]
            if lag.size:
                self.metrics.policy_lag_max = max(self.metrics.policy_lag_max, int(lag.max()))
                self.metrics.policy_lag_sum += int(lag.sum())
                self.metrics.policy_lag_count += int(lag.size)

    def run(
        self,
        agent_steps: int | None = None,
        seconds: float | None = None,
        until: Callable[[ServiceMetrics], bool] | None = None,
        report_every: float = 5.0,
    ) -> ServiceMetrics:
        """Route segments until a budget is met; refreshes metrics every ``report_every`` s."""
        deadline = time.perf_counter() + seconds if seconds is not None else None
        last_report = 0.0
        while True:
            self.step()
            now = time.perf_counter()
            if now - last_report >= report_every:
                self.refresh_metrics()
                last_report = now
            if agent_steps is not None and self.metrics.agent_steps >= agent_steps:
                break
            if deadline is not None and now >= deadline:
                break
            if until is not None and until(self.metrics):
                break
        self._drain_submits(block=False)
        return self.refresh_metrics(wait_s=REPORT_WAIT_S)

    def refresh_metrics(self, wait_s: float = 0.0) -> ServiceMetrics:
        """Aggregate each worker's newest metrics (``WorkerReports``: never blocks on a
        busy or hung worker). ``wait_s``: how long to wait for the calls in flight."""
        self.metrics.take(self._reports.poll(self.workers, wait_s))
        self.metrics.dropped_by_reason = self.ledger.dropped_by_reason()
        self.metrics.seconds = time.perf_counter() - self._started
        return self.metrics
