"""The rollout service on real Ray in local mode (2 CPUs), unitysim over real gRPC."""

from __future__ import annotations

import math
import os
import signal
import time
from collections.abc import Callable
from pathlib import Path

import psutil
import pytest
import ray
from ray.exceptions import ActorUnavailableError, RayTaskError

from driver.training.counting_learner import CountingLearner
from learners.acting.factory import actor_factory
from rollout.collecting.worker import RolloutWorker, WeightsLost
from rollout.environment.restarts import RestartPolicy
from rollout.environment.unity import UnityConfig
from rollout.serving.service import (
    LearnerDied,
    RolloutError,
    RolloutService,
    ServiceConfig,
)
from testkit.synthetic import SyntheticWorker
from tests.helpers import wait_gone
from tests.rollout.test_segments import numpy_segment
from tests.rollout.workers import PORTS, service_config, stop_worker
from tests.waiting import wait_for

pytestmark = pytest.mark.integration


def test_service_routes_segments_and_weights_and_survives_a_killed_worker(ray_session, registry):
    learner = ray_session.remote(CountingLearner).remote(bump_every=2)
    config = service_config(
        UnityConfig("unitysim:3DBall", additional_args=("--no-parent-watch",)), registry
    )
    service = RolloutService(config, actor_factory, learner)
    try:
        service.start()
        service.run(agent_steps=3000)
        victim = ray_session.get(service.workers[0].identity.remote())
        os.kill(victim["pid"], signal.SIGKILL)
        # The launch guard ends the player with its worker (its own parent watch is off).
        assert wait_gone(victim["player_pid"]), "player survived its killed worker"
        before = service.metrics.segments
        metrics = service.run(seconds=15)
        assert metrics.worker_restarts >= 1
        assert metrics.segments > before
        summary = ray_session.get(learner.summary.remote())
    finally:
        service.stop()
        ray_session.kill(learner)
    assert summary["version"] >= 3
    assert len(summary["versions_seen"]) >= 3, "workers picked up newer weights"
    assert summary["steps"]["3DBall?team=0"] >= 3000
    assert metrics.policy_lag_count > 0 and metrics.policy_lag_max >= 0


def test_workers_wait_for_new_weights_once_in_flight_steps_cover_the_demand(ray_session, registry):
    """An on-policy learner wants 600 steps per version and "updates" for 2.5 s. Without
    the demand gate, both workers would act with the old weights all that time (thousands
    of steps); with it, the steps acted by any one version stay within the demand plus
    what collects already under way and rows in progress can add."""
    demand, horizon, workers = 600, 8, 2
    learner = ray_session.remote(CountingLearner).remote(demand=demand, update_seconds=2.5)
    config = service_config(UnityConfig("unitysim:3DBall"), registry, workers, horizon)
    with RolloutService(config, actor_factory, learner) as service:
        service.run(until=lambda m: m.segments > 0, seconds=120)
        service.run(until=lambda m: service.version >= 4, seconds=180)  # 3 versions acted
        summary = ray_session.get(learner.summary.remote())
        rows = service.demand.rows(service.live())
    ray_session.kill(learner)
    # what the workers held in rows, as their collects reported it: within a buffer, so
    # the gate holds (rollout/serving/demand.py)
    assert 0 < rows <= workers * 12 * (horizon - 1) < demand
    # A collect stops after the exchange that reaches its share (one exchange of 3DBall's
    # 12 agents emits at most 12 rows of `horizon`), and rows in progress at a version
    # change carry up to horizon - 1 steps per agent into the next version's count.
    per_collect = math.ceil(demand / workers) + 12 * horizon
    bound = demand + workers * per_collect + workers * 12 * (horizon - 1)
    acted = {v: n for v, n in summary["versions_seen"].items() if v < summary["version"]}
    assert len(acted) >= 3, summary
    assert max(acted.values()) <= bound, (acted, bound)
    # On average only the last exchange of each collect overshoots its share.
    assert sum(acted.values()) / len(acted) <= demand + workers * 12 * horizon, acted


def held_learner(
    ray_session, demand: int
) -> tuple[ray.actor.ActorHandle, Callable[[str], ray.ObjectRef]]:
    """A counting learner whose updates wait for ``release``, and a call of its ``summary``
    or ``release`` on their own concurrency group, as the real learner's status calls
    (``learners.host.remote``): submissions stay one at a time, so a collect submitted
    during a held update waits instead of holding the thread ``summary`` needs."""
    learner = ray_session.remote(concurrency_groups={"status": 1})(CountingLearner).remote(
        demand=demand, hold_updates=True
    )

    def status(method: str) -> ray.ObjectRef:
        return getattr(learner, method).options(concurrency_group="status").remote()

    return learner, status


def test_a_held_learner_answers_its_status_while_a_second_submission_waits(ray_session):
    """Two submissions past the demand (a collect that arrives during the update): the
    second waits for the first, and ``summary`` answers meanwhile (not after the hold's
    120-s safety stop)."""
    learner, status = held_learner(ray_session, demand=10)
    first = learner.submit.remote([numpy_segment(20)])
    wait_for(lambda: ray_session.get(status("summary"))["updating"], "the update to start")
    learner.submit.remote([numpy_segment(20)])  # sent before the summary below
    summary = ray_session.get(status("summary"), timeout=30)
    assert summary["updating"] and summary["version"] == 0 and summary["submissions"] == 1
    ray_session.get(status("release"))
    assert ray_session.get(first, timeout=60) == (1, 10)
    ray_session.kill(learner)


def test_the_driver_gets_control_back_while_the_learner_updates(ray_session, registry):
    """``run(seconds=...)`` returns while the learner's update still runs (the driver reads
    progress and prints summaries meanwhile), instead of blocking on the submission that
    triggered it. The update is held until the test releases it, so "during" is an event:
    a ``run`` that waited for the update would come back only after the hold's safety stop,
    with the version already moved on. (``held_learner``: why the learner's status calls
    have a concurrency group of their own.)"""
    learner, status = held_learner(ray_session, demand=300)
    config = service_config(UnityConfig("unitysim:3DBall"), registry, horizon=8)
    with RolloutService(config, actor_factory, learner) as service:
        back_during_update = 0  # run() calls that came back while the update was held
        for _ in range(240):  # a safety stop: the first update comes after 300 steps
            service.run(seconds=0.5)
            summary = ray_session.get(status("summary"))
            assert summary["version"] == 0, f"run() waited for the learner's update: {summary}"
            back_during_update += summary["updating"]
            if back_during_update == 3:
                break
        assert back_during_update == 3, summary
        ray_session.get(status("release"))
        service.run(until=lambda m: service.version >= 1, seconds=120)
        assert service.version == 1
    ray_session.kill(learner)


def test_synthetic_workers_replay_real_collects_with_no_unity_left(ray_session, registry):
    """benchmarks/speed/bench_central.py's source: recorded 3DBall collects, renumbered and
    stamped with the version each worker was sent, routed and booked like real ones."""
    learner = ray_session.remote(CountingLearner).remote(bump_every=2)
    config = service_config(UnityConfig("unitysim:3DBall"), registry)
    synthetic = ray_session.remote(SyntheticWorker)
    with RolloutService(config, actor_factory, learner, synthetic) as service:
        metrics = service.run(until=lambda m: m.segments >= 40, seconds=120)
        identities = ray_session.get([w.identity.remote() for w in service.workers])
        assert all(i["player_pid"] is None for i in identities)
        assert not any(psutil.Process(i["pid"]).children() for i in identities)
    summary = ray_session.get(learner.summary.remote())
    ray_session.kill(learner)
    assert metrics.segments >= 40
    assert summary["steps"]["3DBall?team=0"] == service.ledger.summary()["delivered"] > 40 * 512
    assert service.ledger.summary()["balanced"]
    assert max(summary["versions_seen"]) >= summary["version"] - 2 > 10  # stamped as sent


def one_restartable_worker(registry: str) -> ServiceConfig:
    """One worker on 3DBall that Ray may restart once; its player ends with it."""
    return service_config(
        UnityConfig("unitysim:3DBall", additional_args=("--no-parent-watch",)),
        registry,
        workers=1,
        max_worker_restarts=1,
    )


def test_a_killed_worker_is_one_failure_however_long_ray_takes_to_restart_it(ray_session, registry):
    """While Ray restarts a worker (seconds: a new process imports torch), collects sent to
    it fail at once as "unavailable"; those retries must not count as more deaths, or a
    budget of one restart would end the run."""
    learner = ray_session.remote(CountingLearner).remote()
    config = one_restartable_worker(registry)
    with RolloutService(config, actor_factory, learner) as service:
        service.run(agent_steps=500)
        victim = ray_session.get(service.workers[0].identity.remote())
        os.kill(victim["pid"], signal.SIGKILL)
        before = service.metrics.segments
        metrics = service.run(until=lambda m: m.segments >= before + 5, seconds=60)
        assert metrics.segments >= before + 5, "the restarted worker never delivered"
        assert metrics.worker_restarts == 1
        assert ray_session.get(service.workers[0].identity.remote())["pid"] != victim["pid"]
    ray_session.kill(learner)


def test_a_learner_killed_while_it_publishes_is_the_learners_death(ray_session, registry):
    """A collect sent the weights a learner is still publishing fails on that argument
    when the learner dies: the learner's death (the driver restores it), not the worker's
    failure that ended the run (seen once in a fresh-clone suite). Then the run goes on."""
    # Two calls at once: a submission is answered while a version is being published, so
    # that when the learner dies, no submission is in flight (it would show the death too)
    # and the worker's one collect waits for weights that never come.
    learner = (
        ray_session.remote(CountingLearner)
        .options(max_concurrency=2)
        .remote(bump_every=1, weights_seconds=120)
    )
    config = service_config(UnityConfig("unitysim:3DBall"), registry, workers=1)
    with RolloutService(config, actor_factory, learner) as service:
        service.run(until=lambda m: service.version >= 1, seconds=120, report_every=0.2)
        before, now = -1, service.metrics.segments
        for _ in range(20):  # until a second brings no segment: the collect waits on weights
            before, now = now, service.run(seconds=1, report_every=0.2).segments
            if now == before:
                break
        assert now == before, "segments kept coming while the new version was held back"
        ray_session.kill(learner, no_restart=True)
        with pytest.raises(LearnerDied):
            service.run(seconds=60, report_every=0.2)
        assert service.metrics.worker_restarts == 0
        restored = ray_session.remote(CountingLearner).remote(bump_every=1)
        ray_session.get(restored.submit.remote([]))
        service.replace_learner(restored)
        metrics = service.run(until=lambda m: m.segments >= 4, seconds=120)
    summary = ray_session.get(restored.summary.remote())
    ray_session.kill(restored)
    assert metrics.segments >= 4 and metrics.worker_restarts == 0
    assert summary["submissions"] >= 1


def test_a_worker_whose_unity_keeps_failing_ends_the_run_with_its_cause(ray_session, registry):
    learner = ray_session.remote(CountingLearner).remote()
    unity = UnityConfig(
        "unitysim:3DBall",
        additional_args=("--sim-crash-after", "2"),
        restarts=RestartPolicy(max_lifetime_restarts=1, backoff_s=0),
    )
    config = service_config(unity, registry, workers=1, horizon=8)
    with (
        RolloutService(config, actor_factory, learner) as service,
        pytest.raises(RolloutError, match=r"worker 0: .*lifetime limit of 1 restarts reached"),
    ):
        service.run(seconds=60)


def test_a_worker_restarted_while_idle_asks_for_the_weights_again(ray_session, registry):
    """No call saw the death, so only the worker can tell that its weights are gone."""
    worker = RolloutWorker.options(num_cpus=0.5, max_restarts=1).remote(
        0, UnityConfig("unitysim:3DBall"), actor_factory, 16, PORTS, registry
    )
    try:
        assert ray_session.get(worker.collect.remote(1, (1, {}), 1))
        assert ray_session.get(worker.collect.remote(1, None, 1)), "version 1 is loaded"
        old = ray_session.get(worker.identity.remote())
        os.kill(old["pid"], signal.SIGKILL)
        assert wait_gone(old["player_pid"])

        def answers() -> bool:  # back once it answers, with its new player
            try:
                return bool(ray_session.get(worker.identity.remote(), timeout=30))
            except ActorUnavailableError:
                return False

        wait_for(answers, "the restarted worker to answer", 240)
        with pytest.raises(RayTaskError) as caught:
            ray_session.get(worker.collect.remote(1, None, 1), timeout=120)
        assert isinstance(caught.value.cause, WeightsLost)
        assert ray_session.get(worker.collect.remote(1, (1, {}), 1)), "resent weights: it acts"
        assert ray_session.get(worker.identity.remote())["pid"] != old["pid"]
    finally:
        stop_worker(ray_session, worker)


def test_a_hung_player_stalls_neither_the_driver_nor_the_run(ray_session, registry):
    """Both players stop answering after 200 steps, on every launch. The driver's loop
    keeps its pace with the workers' last metrics (it used to wait 30 s on a metrics call
    queued behind the hung step, then fail); each hang is found within ``timeout_wait``,
    the player is killed at once and replaced, and collection goes on. ``timeout_wait`` is
    also a relaunched player's time to connect: 15 s was too short for one on two slow
    cores beside the rest of the suite."""
    wait = 30
    learner = ray_session.remote(CountingLearner).remote(bump_every=2)
    unity = UnityConfig(
        "unitysim:3DBall",
        additional_args=("--sim-hang-after", "200"),
        timeout_wait=wait,
        restarts=RestartPolicy(backoff_s=0.0),
    )
    config = service_config(unity, registry)
    with RolloutService(config, actor_factory, learner) as service:
        service.run(agent_steps=1000)
        longest, deadline = 0.0, time.monotonic() + 4 * wait + 60
        while service.metrics.unity_restarts < 2 and time.monotonic() < deadline:
            started = time.monotonic()
            service.run(seconds=1.0)
            longest = max(longest, time.monotonic() - started)
        # the relaunched players may have given their 200 steps before the loop saw the
        # restarts: then the next segments come after the next hang's restart
        before = service.metrics.segments
        service.run(until=lambda m: m.segments > before, seconds=2 * wait + 10)
        assert service.metrics.segments > before, "collection went on after the restarts"
    ray_session.kill(learner)
    assert service.metrics.unity_restarts >= 2
    # relative to the hang's own timeout: a loop that waited on the hung step took ``wait``
    assert longest < wait / 2, f"a run of 1 s took {longest:.1f} s (timeout_wait {wait} s)"


def test_a_build_that_exits_at_once_ends_the_run_at_once(ray_session, registry, tmp_path):
    """Its worker stays alive and says why on its first collect: no actor restarts, no
    relaunches, one line."""
    build = tmp_path / "Game.x86_64"
    build.write_text("#!/bin/sh\nexit 0\n")
    build.chmod(0o755)
    learner = ray_session.remote(CountingLearner).remote()
    config = service_config(UnityConfig(str(build)), registry, workers=1, horizon=8)
    service = RolloutService(config, actor_factory, learner)
    try:
        service.start()
        with pytest.raises(RolloutError, match="exited with code 0 before it connected") as error:
            service.run(seconds=60)
        assert "\n" not in str(error.value) and service.metrics.worker_restarts == 0
    finally:
        service.stop()
        ray_session.kill(learner)


class SlowToRestart(RolloutWorker.__ray_actor_class__):  # type: ignore[name-defined,misc]
    """A worker whose restart takes 3 s longer (as on a loaded machine); each close leaves
    a file beside the port registry, named by the process that closed."""

    def __init__(self, index: int, unity: UnityConfig, *rest: object) -> None:
        if ray.get_runtime_context().was_current_actor_reconstructed:
            time.sleep(3.0)  # the slowness itself, not a wait
        self.closes = Path(str(rest[-1])).parent / "closes"
        super().__init__(index, unity, *rest)

    def close(self):
        closed = super().close()
        self.closes.mkdir(exist_ok=True)
        (self.closes / str(os.getpid())).touch()
        return closed


def test_a_worker_ray_is_restarting_when_the_run_stops_is_closed_once_back(ray_session, registry):
    """Killed mid-start, a restarted worker's new process once outlived the kill and Ray's
    shutdown, holding its port (a fresh-clone suite). Stop waits for it and closes it."""
    learner = ray_session.remote(CountingLearner).remote()
    config = one_restartable_worker(registry)
    worker_class = ray_session.remote(num_cpus=1)(SlowToRestart)
    service = RolloutService(config, actor_factory, learner, worker_class=worker_class)
    try:
        service.start()
        service.run(agent_steps=300)
        victim = ray_session.get(service.workers[0].identity.remote())
        os.kill(victim["pid"], signal.SIGKILL)
        service.run(until=lambda m: m.worker_restarts >= 1, seconds=30)
        assert service.metrics.worker_restarts == 1
    finally:
        service.stop()
        ray_session.kill(learner)
    closes = [int(p.name) for p in (Path(registry).parent / "closes").iterdir()]
    assert len(closes) == 1 and closes[0] != victim["pid"], "the new process was closed"
    assert wait_gone(closes[0])
