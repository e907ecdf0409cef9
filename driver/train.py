"""Training runs: ``build_system`` wires workers, service and learner; ``train`` drives
them until every behavior reaches ``max_steps`` (or a time limit, or a signal).

The data flow is the service's (see ``rollout/service.py``); this file adds what a run
needs around it: the trainer config, the run directory (``<results>/<run id>/``, with
``checkpoints/``, TensorBoard files per behavior, ``configuration.yaml`` and
``summary.json``), checkpoints every ``checkpoint_interval`` steps and at the end,
``--resume`` from the newest checkpoint with the step count intact, and SIGINT/SIGTERM:
finish the current step, write a final checkpoint, stop every process.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, Literal

import ray
import yaml
from ray.exceptions import RayActorError

from driver.learner_keeper import LearnerKeeper
from driver.local_ray import BackgroundRay, init_local_ray
from driver.startup import first_steps, startup_times
from driver.summaries import Summaries, next_multiple
from learners.config import ConfigError, config_for_env, load_config, parse_config
from learners.devices import DeviceError, learner_device
from learners.factory import policy_factory
from learners.remote import learner_actor
from learners.settings import RunConfig
from learners.trainers import trainer
from rollout.membership import request_workers, workers_wanted
from rollout.restarts import RestartPolicy
from rollout.service import (
    LearnerDied,
    RolloutError,
    RolloutService,
    ServiceConfig,
    last_line,
)
from rollout.unity import EngineSettings, UnityConfig, UnityError, resolve_build

log = logging.getLogger(__name__)


class TrainingError(Exception):
    """A one-line problem with the run's options, found before anything starts."""


@dataclass(frozen=True)
class TrainOptions:
    env: str = "unitysim:3DBall"  # unitysim:<Env>, a path to a build, or "editor"
    workers: int | Literal["auto"] = 2  # auto: one per CPU left after the learner's, elastic
    config: str | None = None  # ML-Agents trainer config; default: config/<Env>.yaml
    run_id: str = "run"
    results_dir: str = "results"
    seed: int = 0
    resume: bool = False
    resume_if_exists: bool = False  # resume when the run has a checkpoint, else start fresh
    force: bool = False
    max_steps: int | None = None  # overrides every behavior's max_steps
    max_seconds: float | None = None
    cpus: int = 2  # local mode: ray.init(num_cpus=cpus)
    address: str | None = None  # join an existing Ray cluster instead ("auto" in a job)
    progress: bool = True
    num_areas: int = 1
    restarts: RestartPolicy = field(default_factory=RestartPolicy)  # of each Unity instance
    timeout_wait: int = 60  # seconds for Unity to connect or answer (mlagents-learn's)
    max_learner_restarts: int = 3  # learner deaths a run survives (from its last checkpoint)
    learner_cpus: float = 1.0  # --workers auto: CPUs of the cluster left to the learner
    max_workers: int | None = None  # --workers auto: at most this many (autoscaler's goal)
    collect_ahead: int = 0  # on-policy: steps collected past the learner's demand (service)
    device: str | None = None  # the learner's; None: torch_settings.device, else auto
    mixed_precision: bool = False  # the learner's image encoders in bfloat16 autocast


@dataclass(frozen=True)
class TrainResult:
    run_dir: Path
    steps: dict[str, int]
    version: int
    seconds: float
    checkpoint: Path
    interrupted: bool
    latest: dict[str, dict[str, float | None]]


def load_run_config(options: TrainOptions) -> RunConfig:
    path = Path(options.config) if options.config else config_for_env(options.env)
    try:
        return load_config(path) if path else parse_config({}, "<defaults>")
    except ConfigError as error:
        raise TrainingError(str(error)) from None


def prepare_run_dir(options: TrainOptions) -> tuple[Path, dict[str, Any] | None]:
    """The run directory, and the checkpoint to resume from (None for a fresh run)."""
    run_dir = Path(options.results_dir) / options.run_id
    has_checkpoints = any((run_dir / "checkpoints").glob("*.pt"))
    if options.resume or (options.resume_if_exists and has_checkpoints):
        if not has_checkpoints:
            raise TrainingError(f"--resume: no checkpoint in {run_dir}/checkpoints to resume from")
        from learners import checkpoint  # torch: only a resumed or saving driver loads it

        return run_dir, checkpoint.load(run_dir)
    if has_checkpoints and not options.force:
        raise TrainingError(
            f"{run_dir} already holds a run: pass --resume to continue it, --force to "
            "overwrite it, or choose another --run-id"
        )
    return run_dir, None


def unity_config(options: TrainOptions, config: RunConfig, run_dir: Path) -> UnityConfig:
    build = None if options.env == "editor" else options.env
    if build is None and options.workers != 1:
        raise TrainingError("--env editor: there is one editor (port 5004), so use --workers 1")
    if options.workers != "auto" and options.workers < 1:
        raise TrainingError(f"--workers: at least 1, or auto; got {options.workers}")
    if options.max_workers is not None and (options.workers != "auto" or options.max_workers < 1):
        raise TrainingError("--max-workers: a number of at least 1, with --workers auto")
    if options.timeout_wait < 1:
        raise TrainingError(f"--timeout-wait: at least 1 (seconds), got {options.timeout_wait}")
    try:
        resolve_build(build)
    except UnityError as error:
        raise TrainingError(str(error)) from None
    engine_fields = {f.name for f in dataclasses.fields(EngineSettings)}
    engine = EngineSettings(**{k: v for k, v in config.engine.items() if k in engine_fields})
    return UnityConfig(
        build,
        no_graphics=bool(config.engine.get("no_graphics", True)),  # the one not in EngineSettings
        seed=options.seed,
        num_areas=options.num_areas,
        engine=engine,
        env_params=dict(config.environment_parameters),
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
        seed=options.seed,
        device=device,
        mixed_precision=options.mixed_precision,
    )


def build_system(
    options: TrainOptions,
    config: RunConfig,
    unity: UnityConfig,
    resume: dict[str, Any] | None,
    device: str = "cpu",
) -> tuple[RolloutService, Any]:
    """Learner actor (restored when resuming) and the service with its workers (not started)."""
    learner = start_learner(options, config, device)
    if resume is not None:
        ray.get(learner.load_state_dict.remote(resume))
    elastic = options.workers == "auto"
    if elastic and options.max_workers:
        request_workers(options.max_workers, 1.0, options.learner_cpus)
    if elastic:
        workers = workers_wanted(1.0, options.learner_cpus, options.max_workers)
    else:
        workers = int(options.workers)
    horizons = [s.time_horizon for s in config.behaviors.values()] or [config.default.time_horizon]
    asynchronous = any(trainer(s).asynchronous for s in config.behaviors.values())
    service_config = ServiceConfig(
        unity,
        num_workers=workers,
        horizon=min(horizons),
        collects_per_worker=2 if asynchronous else 1,
        learner_in_flight=4 if asynchronous else 2,
        worker_cpus=1.0 if options.address or elastic else min(1.0, options.cpus / workers),
        elastic=elastic,
        max_workers=options.max_workers,
        learner_cpus=options.learner_cpus,
        await_learner_weights=resume is not None,
        collect_ahead=options.collect_ahead,
    )
    factory = policy_factory(config, options.seed)
    return RolloutService(service_config, factory, learner), learner


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


class Checkpoints:
    """Periodic and final checkpoints in ``<run dir>/checkpoints``, keeping the newest N."""

    def __init__(self, run_dir: Path, interval: int, keep: int, start_step: int) -> None:
        self.directory = run_dir / "checkpoints"
        self.interval, self.keep = interval, max(keep, 1)
        self.next_step = next_multiple(start_step, interval)

    def due(self, step: int) -> bool:
        return step >= self.next_step

    def save(self, state: dict[str, Any], meta: dict[str, Any]) -> Path:
        step = int(state["step"])
        from learners import checkpoint

        path = checkpoint.save(self.directory / f"step-{step:010d}.pt", {**state, "meta": meta})
        self.next_step = next_multiple(step, self.interval)
        for old in sorted(self.directory.glob("step-*.pt"))[: -self.keep]:
            old.unlink(missing_ok=True)
        return path


def train(options: TrainOptions, starting: BackgroundRay | None = None) -> TrainResult:
    """One training run. ``starting``: a local Ray the caller started in the background
    (waited for once the options are checked, left to the caller to stop)."""
    config = load_run_config(options)
    run_dir, resume = prepare_run_dir(options)
    unity = unity_config(options, config, run_dir)
    try:  # before Unity and the learner start: a run that cannot write would lose its checkpoints
        run_dir.mkdir(parents=True, exist_ok=True)
        probe = run_dir / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as error:
        raise TrainingError(
            f"--results-dir: cannot write {run_dir} as uid {os.getuid()} ({error.strerror}); "
            "choose a writable one, or make it writable for this uid (in Docker: mkdir it and "
            "chown it to the uid the container runs as before mounting it)"
        ) from None
    for problem in config.unsupported:
        log.warning("%s: not supported by unity-rollout, ignored", problem)
    (run_dir / "configuration.yaml").write_text(
        yaml.safe_dump(
            {"options": dataclasses.asdict(options), "config": _plain(config)}, sort_keys=False
        )
    )
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
        return _run(options, config, unity, run_dir, resume)
    finally:
        if started_ray:
            ray.shutdown()


def _run(
    options: TrainOptions,
    config: RunConfig,
    unity: UnityConfig,
    run_dir: Path,
    resume: dict[str, Any] | None,
) -> TrainResult:
    behaviors = list(config.behaviors.values()) or [config.default]
    checkpoints = Checkpoints(
        run_dir,
        min(s.checkpoint_interval for s in behaviors),
        max(s.keep_checkpoints for s in behaviors),
        int(resume["step"]) if resume else 0,
    )
    device = choose_device(options, config)
    service, learner = build_system(options, config, unity, resume, device)
    keeper = LearnerKeeper(
        learner,
        lambda: start_learner(options, config, device),
        run_dir,
        options.max_learner_restarts,
    )
    started = time.perf_counter()
    deadline = started + options.max_seconds if options.max_seconds else None
    meta = {"env": options.env, "run_id": options.run_id}
    progress: dict[str, Any] = {"steps": {}, "version": 0}
    with (
        stop_on_signals() as received,
        service,
        Summaries(
            run_dir,
            lambda behavior: config.for_behavior(behavior).summary_freq,
            options.progress,
            start_steps={n: int(b["steps"]) for n, b in resume["behaviors"].items()}
            if resume
            else None,
        ) as summaries,
    ):
        while not received:
            try:
                metrics = service.run(seconds=0.5, report_every=0.5)
                learner = keeper.learner
                progress = ray.get(learner.progress.remote())
                summaries.observe(metrics, progress, ray.get(learner.drain_reports.remote()))
                if checkpoints.due(sum(progress["steps"].values())):
                    checkpoints.save(ray.get(learner.state_dict.remote()), meta)
            except RolloutError:  # keep what was learned, then report the cause
                try:
                    checkpoints.save(ray.get(keeper.learner.state_dict.remote()), meta)
                except RayActorError:  # the learner is gone too: its last checkpoint stays
                    log.warning("no final checkpoint: the learner died with the run")
                raise
            except (LearnerDied, RayActorError) as error:  # only the learner's calls raise it
                keeper.restore(service, _cause(error))
                continue
            if progress["done"] or (deadline is not None and time.perf_counter() >= deadline):
                break
        state = ray.get(keeper.learner.state_dict.remote())  # after every submission sent
        final = checkpoints.save(state, meta)
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
        final,
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
                "checkpoint": str(final),
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


def _cause(error: Exception) -> str:
    """Ray's last line without its paragraph of generic advice."""
    return last_line(error).split(" Some common causes")[0]


def _plain(value: Any) -> Any:
    """Dataclasses, mappings and sequences as plain YAML data (for configuration.yaml)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value
