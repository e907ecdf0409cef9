"""The rollout service: starts N workers, routes their segments to the learner, brings
newer weights back, supervises, aggregates metrics, and stops everything cleanly.

Data flow (ObjectRefs: the learner gets the collect's own ref; the driver reads only its
step counts and policy versions)::

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
loop, unless the workers' rows in progress hold more than a buffer (``rollout/serving/demand.py``).
``collect_ahead`` lets workers go on past the demand, through the update, with the
weights it replaces. Off-policy and V-trace learners answer None and keep every worker busy.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

import ray
from ray.exceptions import ObjectLostError, RayActorError, RayError, RayTaskError

from batches.contracts import ActorFactory
from batches.parameters import Assignment, Values
from rollout.collecting.horizons import Horizons
from rollout.collecting.ledger import LEARNER_RESTART, SHUTDOWN, WORKER_DEATH, Ledger, steps_of
from rollout.collecting.worker import RolloutWorker
from rollout.serving.config import LearnerDied, RolloutError, ServiceConfig, last_line
from rollout.serving.demand import Demand, share
from rollout.serving.membership import Membership
from rollout.serving.metrics import ServiceMetrics, WorkerReports, merge_stats
from rollout.serving.supervision import WorkerSupervision

log = logging.getLogger(__name__)
__all__ = ["LearnerDied", "RolloutError", "RolloutService", "ServiceConfig", "last_line"]


REPORT_WAIT_S = 2.0  # at the end of ``run``: for metrics of workers between collects


class RolloutService(WorkerSupervision):
    def __init__(
        self,
        config: ServiceConfig,
        actor_factory: ActorFactory,
        learner: ray.actor.ActorHandle,
        worker_class: Any = RolloutWorker,  # a Ray actor class with RolloutWorker's calls
    ) -> None:
        self.config = config
        self.worker_class = worker_class
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
        self.demand = Demand()
        self._failures: list[int] = []  # consecutive failed collects per worker
        self._restarting: dict[int, float] = {}  # worker index -> when it went away
        self._counted_unseen: set[int] = set()  # restarts WeightsLost counted before arrival
        self._retry_at: dict[int, float] = {}  # worker index -> when to ask it again
        self._reports = WorkerReports()
        self._stale: set[ray.ObjectRef] = set()  # collects acted by a dead learner's weights
        self._dead_learners: set[str] = set()  # actor ids of learners replaced
        self._assignment: Assignment | None = None  # environment parameters after a lesson
        self._started = 0.0
        self.membership = (
            Membership(
                config.worker_cpus,
                config.learner_cpus,
                config.max_workers,
                max_barren=config.max_worker_restarts,
            )
            if config.elastic
            else None
        )

    # --- lifecycle ----------------------------------------------------------------------

    def _make_worker(self, index: int) -> ray.actor.ActorHandle:
        config = self.config
        return self.worker_class.options(
            num_cpus=config.worker_cpus,
            max_restarts=0 if config.elastic else config.max_worker_restarts,
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
        self.demand = Demand()  # these workers' rows, from their first collects on
        # Workers first: their processes and Unity players start while the learner's does.
        self.workers = [self._make_worker(i) for i in range(self.config.num_workers)]
        if self.membership is not None:
            self.membership.started = len(self.workers)
        first = self.learner.submit.remote([])  # (version, demand), as every submit answers
        if self.config.await_learner_weights:
            self._weights_ref = self.learner.weights.remote()
            self._version = int(ray.get(self._weights_ref)[0])
            self.demand.answered(ray.get(first)[1])
        else:  # answered whenever the learner is up, like any submission
            self._version = 0
            self.demand.answered(None)
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

    def live(self) -> list[int]:
        """Indices of the workers not retired (elastic: those that left are)."""
        retired = self.membership.retired if self.membership else set()
        return [i for i in range(len(self.workers)) if i not in retired]

    def stop(self) -> None:
        """Close every worker's Unity instance, then end the actors."""
        live = self.live()
        if self.membership is not None:  # a joiner may wait for room that never comes
            live = [i for i in live if i in self.membership.delivered]
        closed = self._close(live)
        self._drain_submits(block=False, timeout=10.0, lost=SHUTDOWN)
        finished, _ = ray.wait(list(self._collects), num_returns=len(self._collects), timeout=0)
        for ref in finished:  # read, so that Ray does not report their errors as unhandled
            with contextlib.suppress(Exception):
                collected = ray.get(ref)
                index = self._collects[ref][0]
                self.ledger.arrived(index, collected)
                self.ledger.book(index, collected.incarnation, steps_of(collected), SHUTDOWN)
        for index in live:
            if not isinstance(last := closed[index], Exception):
                self.ledger.ended(index, SHUTDOWN, last)
                continue
            log.warning("while closing worker %d: %s", index, last_line(last))
            self.ledger.ended(index, WORKER_DEATH if isinstance(last, RayActorError) else SHUTDOWN)
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
            self._version, weights, steps, self.config.max_collect_s, self._assignment
        )
        self._worker_version[index] = self._version
        self._collects[ref] = (index, steps)

    def set_environment_parameters(self, values: Values, reset: bool = False) -> None:
        """A lesson changed: every collect from now on carries the run's current values
        (all of them: a worker Ray restarts starts from the first lesson's), and each
        worker applies them once, between collects."""
        number = self._assignment.number + 1 if self._assignment is not None else 1
        self._assignment = Assignment(number, dict(values), reset)

    def _pump(self) -> None:
        """Give idle workers a collect, as far as the learner's demand reaches."""
        idle = [i for i in self._idle if i not in self._retry_at]
        if not idle:
            return
        if self.demand.wanted is None:
            for index in idle:
                self._issue(index)
            self._idle.difference_update(idle)
            return
        if self.demand.wanted == 0:
            return  # the learner has every step the run needs: none ahead either
        coming = sum(steps for _, steps in self._collects.values())
        coming += sum(sum(steps.values()) for _, _, steps in self._books.values())
        missing = self.demand.missing(coming, self.live(), self.config.collect_ahead)
        if missing <= 0:
            return  # in flight already fills the next update: wait for its weights
        each = share(missing, len(idle), Horizons.of(self.config.horizon).shortest)
        for index in idle:
            self._issue(index, each)
        self._idle.difference_update(idle)

    def step(self, timeout: float = 60.0) -> int:
        """Route one finished collect to the learner; returns the segments routed (0 when
        the learner stays busy through ``timeout``, so that the caller can read its status)."""
        if self.membership is not None:
            self._grow()
        full = len(self._submits) >= self.config.learner_in_flight
        self._drain_submits(block=full, timeout=timeout)
        if len(self._submits) >= self.config.learner_in_flight:
            return 0  # the learner is still busy (an update): the caller may look at it now
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
        except RayError as error:
            return self._collect_failed(index, ref, error)
        if self.ledger.arrived(index, segments) and not self._take_counted(index):
            # it died idle and new weights reached its new incarnation: no call failed
            self.metrics.worker_restarts += 1
            log.warning("worker %d was restarted by Ray while idle", index)
        self.demand.rows_seen(index, segments.counts)
        if ref in self._stale:  # weights the restored learner never had: drop
            self._stale.discard(ref)
            self.ledger.book(index, segments.incarnation, steps_of(segments), LEARNER_RESTART)
            segments = []
        if self.membership is not None:
            self.membership.delivered_by(index)
        self._failures[index] = 0
        self._restarting.pop(index, None)
        self._idle.add(index)
        if segments:
            submit = self.learner.submit.remote(ref)
            self._submits.append(submit)
            self._books[submit] = (index, segments.incarnation, steps_of(segments))
            self.metrics.observe(self._version, segments)
        return len(segments)

    def _drain_submits(
        self, block: bool, timeout: float | None = None, lost: str | None = None
    ) -> None:
        """Take the learner's answers; ``lost``: the reason to book what does not come
        back within ``timeout`` (at shutdown), instead of waiting for it."""
        if not self._submits:
            return
        ready, _ = ray.wait(
            self._submits,
            num_returns=1 if block else len(self._submits),
            timeout=timeout if (block or lost) else 0,
        )
        if ready:  # and every other answer already in
            ready, _ = ray.wait(self._submits, num_returns=len(self._submits), timeout=0)
        # The learner's newest answer is its state: answers taken in the order asked (not
        # ray.wait's), none past one still out, so an older one never overwrites a newer.
        arrived, done = set(ready), []
        for ref in self._submits:
            if ref not in arrived and not lost:
                break
            if ref in arrived:
                done.append(ref)
        taken = set(done)
        self._submits = [ref for ref in self._submits if ref not in taken]
        try:
            answers = ray.get(done)
        except RayActorError as error:
            if lost is None:
                raise LearnerDied(last_line(error)) from None
            self._submits += done  # booked as lost below
            done, answers = [], []
        except RayTaskError as error:  # the learner refused what it was given, and lives on
            raise RolloutError(f"the learner: {last_line(error)}") from None
        except ObjectLostError:  # a collect's data died with its worker's node on the way
            done, answers = self._answers_left(done)
        for ref in self._submits if lost else []:
            if ref in self._books:
                self.ledger.book(*self._books.pop(ref), lost)
        for ref, (version, wanted) in zip(done, answers, strict=True):
            if ref in self._books:
                self.ledger.book(*self._books.pop(ref), "delivered")
            self.demand.answered(wanted)
            if version > self._version:
                self._version = version
                self._weights_ref = self.learner.weights.remote()

    def _answers_left(self, done: list[ray.ObjectRef]) -> tuple[list, list]:
        """The submissions that answered, the rest booked as lost with their worker."""
        kept, answers = [], []
        for ref in done:
            try:
                answers.append(ray.get(ref))
                kept.append(ref)
            except ObjectLostError:
                if ref in self._books:
                    self.ledger.book(*self._books.pop(ref), WORKER_DEATH)
        return kept, answers

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
        self.demand.answered(ray.get(learner.submit.remote([]))[1])

    def ask_learner(self) -> None:
        """Have the learner state its version and demand now, not with the next delivery:
        its demand may have grown with no data coming (a consumer took its batches)."""
        self._submits.append(self.learner.submit.remote([]))

    @property
    def version(self) -> int:
        """The newest weights version the service has seen published."""
        return self._version

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
            left = report_every if deadline is None else deadline - time.perf_counter()
            self.step(max(0.0, min(report_every, left)))  # back for the checks below
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
        live = set(self.live())
        workers = [w if i in live else None for i, w in enumerate(self.workers)]
        self.metrics.take(self._reports.poll(workers, wait_s))
        merge_stats(self.metrics.unity_stats, self._reports.drain_stats())
        self.metrics.dropped_by_reason = self.ledger.dropped_by_reason()
        self.metrics.seconds = time.perf_counter() - self._started
        return self.metrics
