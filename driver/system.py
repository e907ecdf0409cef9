"""A run's system wired from its options and trainer config: what every Unity instance
gets, the learner actor and the service with its workers (not yet started). The CLI's
``train`` and a Tune trial (``driver/tuning/trial.py``) build theirs the same way,
``collect`` its counting one, and ``record-demo`` its one Unity instance's config."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import ray

from batches.expert_steps import ExpertSteps
from driver.declaration import TrainingError
from driver.options import CollectOptions, RecordDemoOptions, TrainOptions, build_of
from driver.training.curriculum import LessonPlan, lesson_plan
from driver.training.learner_keeper import initialize_into, load_into
from driver.training.planner import Start
from learners.acting.factory import actor_factory, policy_factory
from learners.host.devices import DeviceError, learner_device
from learners.host.remote import learner_actor
from learners.trainer_config.settings import RunConfig, TrainerSettings
from learners.trainer_config.trainer_types import trainer
from rollout.collecting.horizons import Horizons
from rollout.environment.ports import PortRange
from rollout.environment.unity import EngineSettings, UnityConfig
from rollout.serving.membership import request_workers, workers_wanted
from rollout.serving.service import RolloutService, ServiceConfig


def unity_config(
    options: TrainOptions, config: RunConfig, run_dir: Path, lessons: LessonPlan | None = None
) -> UnityConfig:
    """What every Unity instance gets: the trainer config's engine_settings, the command
    line's engine options over them (as mlagents-learn), the run's seed and arguments, the
    environment parameters of the run's lessons (the first ones, unless resumed)."""
    lessons = lessons or lesson_plan(options, config, None)
    engine_fields = {f.name for f in dataclasses.fields(EngineSettings)}
    given = {k: v for k, v in config.engine.items() if k in engine_fields}
    given |= {k: v for k in engine_fields if (v := getattr(options, k)) is not None}
    return UnityConfig(
        build_of(options.env),
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


def configured(config: RunConfig) -> list[TrainerSettings]:
    """Every behavior's settings the config gives, its default_settings included."""
    return [*config.behaviors.values(), *([config.default] if config.default_given else [])]


def learner_threads(options: TrainOptions, config: RunConfig) -> int:
    """The learner's torch threads: ``--learner-threads``, else OMP_NUM_THREADS where the
    driver has it; else 0 (every core the learner may keep busy) where the workers wait
    through each update (on-policy trainers, nothing collected ahead), else 1 (workers
    collect beside it). POCA's 512-wide SoccerTwos config trained 1.5 times as fast with
    2 threads as with 1 on 2 cores; 3DBall's and DungeonEscape's small networks the same."""
    if options.learner_threads is not None:
        return options.learner_threads
    if (omp := os.environ.get("OMP_NUM_THREADS", "")).isdigit() and int(omp) > 0:
        return int(omp)
    given = configured(config)
    waits = all(trainer(s).waits_for_fresh_data for s in given) or not given
    return 0 if waits and not options.collect_ahead and not threaded_ahead(config) else 1


def start_learner(
    options: TrainOptions,
    config: RunConfig,
    device: str,
    experts: Mapping[str, ExpertSteps],
    initial: dict[str, Any] | None = None,
) -> Any:
    """The learner actor; ``experts``: the run's demonstrations (``Plan.experts``);
    ``initial``: another run's networks it starts from (``Start.initial``). The driver
    starts one this way at the run's start and again when one dies before the first
    checkpoint, so both start from the same networks."""
    learner = learner_actor(
        config,
        options.max_steps,
        torch_threads=learner_threads(options, config),
        seed=options.seed,
        device=device,
        mixed_precision=options.mixed_precision,
        inference=options.inference,
        experts=experts,
    )
    if initial is not None:
        initialize_into(learner, initial)
    return learner


def service_config(
    options: TrainOptions,
    config: RunConfig,
    unity: UnityConfig,
    resume: bool,
    worker_cpus: float | None = None,
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
        worker_cpus=worker_cpus
        or (1.0 if options.address or elastic else min(1.0, options.cpus / workers)),
        elastic=elastic,
        max_workers=options.max_workers,
        learner_cpus=options.learner_cpus,
        await_learner_weights=resume,
        collect_ahead=max(options.collect_ahead, threaded_ahead(config)),
        port_range=ports_from(options.base_port),
    )


def threaded_ahead(config: RunConfig) -> int:
    """Steps workers may collect past an on-policy update's demand for the behaviors that
    set ``threaded``: the largest of their buffers. ML-Agents' threaded trainer updates
    while its environments step on with the old policy (its queue holds 20 trajectories);
    the steps acted meanwhile train the next update, their lag corrected by PPO's ratio."""
    given = configured(config)
    return max(
        (
            s.hyperparameters.buffer_size
            for s in given
            if s.threaded and trainer(s).waits_for_fresh_data
        ),
        default=0,
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
    experts: Mapping[str, ExpertSteps],
    device: str = "cpu",
    worker_cpus: float | None = None,
) -> tuple[RolloutService, Any]:
    """Learner actor (restored when resuming, from another run's networks when
    initialized) and the service with its workers (not started), which wait for the
    learner's weights when it does not start from the factory's. ``experts``: the run's
    demonstrations (``Plan.experts``); ``worker_cpus``: each worker's share, where the
    caller sizes it (a Tune trial's placement group)."""
    initial = start.initial if start.resume is None else None
    learner = start_learner(options, config, device, experts, initial)
    if start.resume is not None:
        load_into(learner, start.resume)
    awaits = start.resume is not None or start.initial is not None
    settings = service_config(options, config, unity, awaits, worker_cpus)
    return RolloutService(settings, policy_factory(config, options.seed), learner), learner


def build_collect_system(options: CollectOptions) -> tuple[RolloutService, Any]:
    """``unity-rollout collect``'s system: the workers feeding a counting learner, which
    never trains (a pipeline check), and the learner actor."""
    from driver.training.counting_learner import CountingLearner

    learner = ray.remote(CountingLearner).options(num_cpus=0).remote()
    local_share = min(1.0, options.cpus / options.workers)
    config = ServiceConfig(
        UnityConfig(build_of(options.env), seed=options.seed),
        num_workers=options.workers,
        horizon=options.horizon,
        worker_cpus=1.0 if options.address else local_share,
    )
    return RolloutService(config, actor_factory, learner), learner


def record_unity_config(options: RecordDemoOptions) -> UnityConfig:
    """What ``record-demo``'s one Unity instance gets (it runs in the command's process:
    no Ray, no learner)."""
    return UnityConfig(
        build_of(options.env),
        seed=options.seed,
        no_graphics=options.no_graphics,
        timeout_wait=options.timeout_wait,
    )
