"""Training runs: ``build_system`` wires workers, service and learner; ``train`` drives
them until every behavior reaches ``max_steps`` (or a time limit, or a signal).

The data flow is the service's (see ``rollout/service.py``); this file adds what a run
needs around it: the run directory opened (``driver/run_dir.py``), each behavior's
checkpoints (``driver/checkpoints.py``) and summaries (``driver/summaries.py``), a dead
learner brought back (``driver/learner_keeper.py``), ``--resume`` from the newest
checkpoints with the step counts intact, and SIGINT/SIGTERM: finish the current step,
write a final checkpoint, stop every process.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import signal
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

import ray
from ray.exceptions import RayActorError

from driver.behavior_notes import BehaviorNotes
from driver.checkpoints import Checkpoints
from driver.curriculum import LessonPlan, lesson_plan
from driver.declaration import TrainingError
from driver.learner_keeper import LearnerKeeper, load_into
from driver.local_ray import BackgroundRay, init_local_ray
from driver.options import TrainOptions
from driver.run_dir import Plan, Start, open_run, plan
from driver.startup import first_steps, startup_times
from driver.summaries import Summaries
from learners.devices import DeviceError, learner_device
from learners.factory import policy_factory
from learners.remote import learner_actor
from learners.settings import RunConfig
from learners.trainers import trainer
from rollout.horizons import Horizons
from rollout.membership import request_workers, workers_wanted
from rollout.ports import PortRange
from rollout.service import (
    LearnerDied,
    RolloutError,
    RolloutService,
    ServiceConfig,
    last_line,
)
from rollout.unity import EngineSettings, UnityConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainResult:
    run_dir: Path
    steps: dict[str, int]
    version: int
    seconds: float
    checkpoint: Path
    interrupted: bool
    latest: dict[str, dict[str, float | None]]


def unity_config(
    options: TrainOptions, config: RunConfig, run_dir: Path, lessons: LessonPlan | None = None
) -> UnityConfig:
    """What every Unity instance gets: the trainer config's engine_settings, the command
    line's engine options over them (as mlagents-learn), the run's seed and arguments, the
    environment parameters of the run's lessons (the first ones, unless resumed)."""
    lessons = lessons or lesson_plan(options, config, None)
    build = None if options.env == "editor" else options.env
    engine_fields = {f.name for f in dataclasses.fields(EngineSettings)}
    given = {k: v for k, v in config.engine.items() if k in engine_fields}
    given |= {k: v for k in engine_fields if (v := getattr(options, k)) is not None}
    return UnityConfig(
        build,
        # the engine settings a player takes as arguments, not through a side channel
        no_graphics=options.no_graphics or bool(config.engine.get("no_graphics", False)),
        no_graphics_monitor=options.no_graphics_monitor
        or bool(config.engine.get("no_graphics_monitor", False)),
        seed=options.seed,
        num_areas=options.num_areas,
        engine=EngineSettings(**given),
        env_params=lessons.values(),
        additional_args=options.env_args,
        log_folder=str(run_dir / "unity-logs"),
        restarts=options.restarts,
        timeout_wait=options.timeout_wait,
    )


def choose_device(options: TrainOptions, config: RunConfig) -> str:
    """The learner's device, chosen once per run: on a GPU when asked or (auto) when the
    cluster has one. A restarted learner gets the same, so it waits for a GPU node to
    come back rather than moving to the CPU or failing."""
    requested = options.device or config.torch_device or "auto"
    try:
        return learner_device(requested, ray.cluster_resources().get("GPU", 0))
    except DeviceError as error:
        raise TrainingError(str(error)) from None


def start_learner(options: TrainOptions, config: RunConfig, device: str) -> Any:
    return learner_actor(
        config,
        options.max_steps,
        torch_threads=options.learner_threads,
        seed=options.seed,
        device=device,
        mixed_precision=options.mixed_precision,
        inference=options.inference,
    )


def service_config(
    options: TrainOptions, config: RunConfig, unity: UnityConfig, resume: bool
) -> ServiceConfig:
    """How the service runs the workers: their number (elastic: from the cluster), each
    behavior's time horizon, and how much a learner of these trainer types takes at once."""
    elastic = options.workers == "auto"
    if elastic and options.max_workers:
        request_workers(options.max_workers, 1.0, options.learner_cpus)
    if elastic:
        workers = workers_wanted(1.0, options.learner_cpus, options.max_workers)
    else:
        workers = int(options.workers)
    horizons = Horizons(
        config.default.time_horizon,
        {name: s.time_horizon for name, s in config.behaviors.items()},
    )
    asynchronous = any(trainer(s).asynchronous for s in config.behaviors.values())
    return ServiceConfig(
        unity,
        num_workers=workers,
        horizon=horizons,
        collects_per_worker=2 if asynchronous else 1,
        learner_in_flight=4 if asynchronous else 2,
        worker_cpus=1.0 if options.address or elastic else min(1.0, options.cpus / workers),
        elastic=elastic,
        max_workers=options.max_workers,
        learner_cpus=options.learner_cpus,
        await_learner_weights=resume,
        collect_ahead=options.collect_ahead,
        port_range=ports_from(options.base_port),
    )


def ports_from(base_port: int | None) -> PortRange | None:
    """mlagents-learn's --base-port: ports from it up (a restarted instance takes a fresh
    one, so a range of them); None: UNITY_ROLLOUT_PORT_RANGE or the default range."""
    return None if base_port is None else PortRange(base_port, min(base_port + 99, 65535))


def build_system(
    options: TrainOptions,
    config: RunConfig,
    unity: UnityConfig,
    start: Start,
    device: str = "cpu",
) -> tuple[RolloutService, Any]:
    """Learner actor (restored when resuming, from another run's networks when
    initialized) and the service with its workers (not started), which wait for the
    learner's weights when it does not start from the factory's."""
    learner = start_learner(options, config, device)
    if start.resume is not None:
        load_into(learner, start.resume)
    elif start.initial is not None:
        ray.get(learner.prepare.remote())  # as load_into: built before tensors arrive
        ray.get(learner.initialize.remote(start.initial))
    awaits = start.resume is not None or start.initial is not None
    settings = service_config(options, config, unity, awaits)
    return RolloutService(settings, policy_factory(config, options.seed), learner), learner


@contextmanager
def stop_on_signals() -> Iterator[list[str]]:
    """SIGINT/SIGTERM set a flag the loop checks, so it can checkpoint before leaving."""
    received: list[str] = []

    def handler(signum: int, frame: FrameType | None) -> None:
        received.append(signal.Signals(signum).name)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield received
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


def train(
    options: TrainOptions, starting: BackgroundRay | None = None, planned: Plan | None = None
) -> TrainResult:
    """One training run. ``starting``: a local Ray the caller started in the background
    (waited for once the run's directory is open, left to the caller to stop);
    ``planned``: ``run_dir.plan(options)``, when the caller checked it before Ray."""
    planned = planned or plan(options)
    options = planned.options  # with what the trainer config's run-level sections give
    start = planned.start or open_run(planned)
    config, run_dir = planned.config, planned.run_dir
    lessons = lesson_plan(options, config, start.resume)
    unity = unity_config(options, config, run_dir, lessons)
    started_ray = False
    if starting is not None:
        starting.wait()
    elif not ray.is_initialized():
        if options.address:
            ray.init(address=options.address, log_to_driver=False)
        else:
            init_local_ray(options.cpus)
        started_ray = True
    try:
        return _run(options, config, unity, run_dir, start, lessons)
    finally:
        if started_ray:
            ray.shutdown()


def _run(
    options: TrainOptions,
    config: RunConfig,
    unity: UnityConfig,
    run_dir: Path,
    start: Start,
    lessons: LessonPlan,
) -> TrainResult:
    resume = start.resume
    start_steps = {n: int(b["steps"]) for n, b in resume["behaviors"].items()} if resume else {}
    checkpoints = Checkpoints(run_dir, config, start_steps, writes=not options.inference)
    device = choose_device(options, config)
    service, learner = build_system(options, config, unity, start, device)
    keeper = LearnerKeeper(
        learner,
        lambda: start_learner(options, config, device),
        run_dir,
        options.max_learner_restarts,
    )
    started = time.perf_counter()
    deadline = started + options.max_seconds if options.max_seconds else None
    meta = {"env": options.env, "run_id": options.run_id, "lessons": lessons.lessons}
    lessons.log_lessons()
    notes = BehaviorNotes(config, unity.no_graphics)
    progress: dict[str, Any] = {"steps": {}, "version": 0}
    with (
        stop_on_signals() as received,
        service,
        Summaries(
            run_dir,
            lambda behavior: config.for_behavior(behavior).summary_freq,
            options.progress,
            start_steps=start_steps,
        ) as summaries,
    ):
        summaries.lessons = lessons.lessons  # the plan's own dict: updated in place
        met: set[str] = set()
        while not received:
            try:
                metrics = service.run(seconds=0.5, report_every=0.5)
                learner = keeper.learner
                progress = ray.get(learner.progress.remote())
                notes.report(metrics.specs)
                if set(metrics.specs) - met:  # new behaviors: self-play teams join now
                    met |= set(metrics.specs)
                    learner.meet.remote(dict(metrics.specs))
                changed, reset = lessons.update(progress["steps"], metrics.episode_totals())
                if changed:
                    service.set_environment_parameters(lessons.values(), reset)
                summaries.observe(metrics, progress, ray.get(learner.drain_reports.remote()))
                if due := checkpoints.due(progress["steps"]):
                    checkpoints.save(ray.get(learner.state_dict.remote(due)), meta)
            except RolloutError as error:  # keep what was learned, then report the cause
                kept = _keep_what_was_learned(keeper, checkpoints, meta)
                raise RolloutError(f"{error} ({kept})") from error
            except (LearnerDied, RayActorError) as error:  # only the learner's calls raise it
                keeper.restore(service, _cause(error))
                continue
            if progress["done"] or (deadline is not None and time.perf_counter() >= deadline):
                break
        state = ray.get(keeper.learner.state_dict.remote())  # after every submission sent
        checkpoints.save(state, meta)
        # what the final checkpoint holds: the loop's last progress may predate submissions
        # still queued at the learner (its status calls do not wait for them)
        progress["steps"] = {name: b["steps"] for name, b in state["behaviors"].items()}
        progress["version"] = state["version"]
        latest = summaries.latest()
        startup = startup_times(first_steps(service), summaries.first_reward_at)
    result = TrainResult(
        run_dir,
        dict(progress["steps"]),
        int(progress["version"]),
        time.perf_counter() - started,
        checkpoints.directory,
        bool(received),
        latest,
    )
    stats = progress.get("stats")  # segments Ray delivered twice, taken once
    duplicates = stats.duplicate_steps if stats is not None else 0
    (run_dir / "summary.json").write_text(
        json.dumps(
            {
                "steps": sum(result.steps.values()),
                "behaviors": {
                    name: {"steps": steps, **latest.get(name, {})}
                    for name, steps in result.steps.items()
                },
                "version": result.version,
                "seconds": round(result.seconds, 1),
                "checkpoint": str(checkpoints.directory) if checkpoints.writes else None,
                "interrupted": received[0] if received else None,
                "faults": {**service.metrics.faults(), "duplicate_steps": duplicates},
                "ledger": service.ledger.summary(),
                "membership": service.membership and service.membership.summary(),
                "startup": startup,
            },
            indent=2,
        )
    )
    return result


def _keep_what_was_learned(
    keeper: LearnerKeeper, checkpoints: Checkpoints, meta: dict[str, Any]
) -> str:
    """A last checkpoint of a failed run, when it learned anything; what a retry finds."""
    try:
        state = ray.get(keeper.learner.state_dict.remote())
    except RayActorError:
        return "the learner died with the run: its last checkpoint stays"
    if not checkpoints.writes:
        return "--inference: no checkpoint"
    if not any(int(entry["steps"]) for entry in state["behaviors"].values()):
        return "nothing was trained and no checkpoint written: the same command starts it anew"
    checkpoints.save(state, meta)
    return "a checkpoint was kept: --resume continues from it"


def _cause(error: Exception) -> str:
    """Ray's last line without its paragraph of generic advice."""
    return last_line(error).split(" Some common causes")[0]
