"""``unity-rollout tune``: a Ray Tune search over trainer-config keys, every trial a full
run (``driver/tuning/trial.py``), the trials sharing the nodes through the port registry.

Where it writes, under ``<results>/<run id>/``:
- ``trials/<trial id>/``: each trial's run, as ``train`` writes one (checkpoints,
  TensorBoard files, ``summary.json``), with its ``trainer_config.yaml``;
- ``tune/``: Tune's own experiment (results per report, its checkpoints);
- ``trials.csv``: a line per trial, its values, steps and last reward;
- ``best.yaml``: the best trial's trainer config, ready for ``unity-rollout train``.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import random
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from driver.declaration import TrainingError, from_settings
from driver.options import TrainOptions, TuneOptions
from driver.training.planner import check_environment, settle
from driver.tuning.search import Search, check_search, load_search, with_values
from learners.trainer_config.parse import (
    ConfigError,
    config_for_env,
    parse_config,
    read_config_data,
)
from rollout.environment.builds import UNITYSIM_PREFIX

CHDIR = "RAY_CHDIR_TO_TRIAL_DIR"
HEAD_CPUS = 0.01  # the trial's own actor: it waits on its run, as the CLI's driver does


@dataclass(frozen=True)
class TunePlan:
    options: TrainOptions  # every trial's, before its own config, run id and seed
    tuning: TuneOptions
    search: Search
    config_data: dict[str, Any]
    root: Path
    metric_behavior: str
    report_every: int
    max_steps: int


@dataclass(frozen=True)
class TuneResult:
    root: Path
    trials: int
    errors: int
    best_trial: str | None
    best_reward: float | None
    best_config: Path | None


def plan_tune(options: TrainOptions, tuning: TuneOptions) -> TunePlan:
    """Everything checked before Ray starts; ``TrainingError`` is one line."""
    check_environment()
    for flag, given in (
        ("--resume", options.resume or options.resume_if_exists),
        ("--initialize-from", options.initialize_from),
        ("--inference", options.inference),
        ("--workers auto", options.workers == "auto"),
    ):
        if given:
            raise TrainingError(f"{flag}: not available with tune; each trial is a new run")
    shipped = config_for_env(options.env.removeprefix(UNITYSIM_PREFIX))
    path = options.config or shipped
    try:
        data = read_config_data(path) if path else {}
        config = parse_config(data, str(path or "<defaults>"))
    except ConfigError as error:
        raise TrainingError(str(error)) from None
    options = settle(from_settings(options, config.run_settings, config.source).validate())
    # a trial may run on another node, from another folder: its paths are absolute
    build = options.env
    if build != "editor" and not build.startswith(UNITYSIM_PREFIX):
        build = str(Path(build).resolve())
    options = dataclasses.replace(
        options, results_dir=str(Path(options.results_dir).resolve()), env=build
    )
    search = load_search(str(tuning.search))
    check_search(search, data, str(path or "<defaults>"))
    if tuning.scheduler == "pbt":
        search.check_for_pbt()
    metric = tuning.metric_behavior or next(iter(config.behaviors), None)
    if metric is None:
        raise TrainingError("--metric-behavior: name the behavior whose reward ranks trials")
    settings = config.for_behavior(metric)
    root = Path(options.results_dir) / options.run_id
    if root.exists() and any(root.iterdir()):
        if not options.force:
            raise TrainingError(
                f"{root} already holds a run: pass --force to overwrite it, or choose "
                "another --run-id"
            )
        shutil.rmtree(root)
    return TunePlan(
        options,
        tuning,
        search,
        dict(data or {}),
        root,
        metric,
        tuning.report_every or settings.summary_freq,
        options.max_steps or settings.max_steps,
    )


def tune_run(planned: TunePlan) -> TuneResult:
    """The search, on a local Ray of ``--cpus`` or the cluster at ``--address``."""
    import ray

    from driver.local_ray import init_local_ray

    options = planned.options
    started = not ray.is_initialized()
    # trials stay where the command runs: relative paths in the config (demo_path,
    # init_path) mean what they mean to train (Tune would move each into its own folder)
    stay = {CHDIR: "0"}
    if started and options.address:
        ray.init(address=options.address, log_to_driver=False, runtime_env={"env_vars": stay})
    elif started:
        os.environ.update(stay)
        init_local_ray(options.cpus)
    try:
        return _fit(planned)
    finally:
        if started:
            ray.shutdown()


def _fit(planned: TunePlan) -> TuneResult:
    from ray import tune
    from ray.tune.search import BasicVariantGenerator

    from driver.tuning.trial import TrialBase, UnityTrial

    options, tuning = planned.options, planned.tuning
    random.seed(options.seed)  # PBT's explore draws from Python's generator
    worker_cpus, bundles = _trial_resources(options, tuning)
    base = TrialBase(
        dataclasses.replace(options, device=options.device or "cpu"),
        planned.config_data,
        planned.root,
        planned.metric_behavior,
        planned.report_every,
        worker_cpus,
    )
    trainable = tune.with_resources(
        tune.with_parameters(UnityTrial, base=base),
        tune.PlacementGroupFactory(bundles, strategy="PACK"),
    )
    tuner = tune.Tuner(
        trainable,
        param_space=planned.search.space(),
        tune_config=tune.TuneConfig(
            metric="reward",
            mode="max",
            num_samples=tuning.trials,
            scheduler=_scheduler(planned),
            search_alg=BasicVariantGenerator(random_state=options.seed),
            max_concurrent_trials=tuning.concurrent_trials,
            reuse_actors=False,
        ),
        run_config=tune.RunConfig(
            name="tune",
            storage_path=str(planned.root),
            # PBT exploits a better trial's checkpoint from that trial's last perturbation;
            # by then it may have saved two more, and a deleted one fails the exploiting
            # trial (seen on a loaded machine): under PBT every checkpoint is kept
            checkpoint_config=tune.CheckpointConfig(
                num_to_keep=None if tuning.scheduler == "pbt" else 2
            ),
            verbose=1,
        ),
    )
    results = tuner.fit()
    return _write_results(planned, results)


def _trial_resources(
    options: TrainOptions, tuning: TuneOptions
) -> tuple[float, list[dict[str, float]]]:
    """Each trial's placement group: a sliver for its own actor, a bundle per worker (one
    CPU on a cluster; locally ``--cpus`` shared by the trials that run at once), and one
    GPU for a learner asked onto one. The learner itself asks for no CPU, as in a run."""
    workers = int(options.workers)
    if options.address:
        worker_cpus = 1.0
    else:
        at_once = _at_once(tuning)
        worker_cpus = min(1.0, (options.cpus / at_once - HEAD_CPUS) / workers)
        if worker_cpus <= 0:
            raise TrainingError(f"--cpus {options.cpus}: too few for {at_once} trials at once")
    bundles = [{"CPU": HEAD_CPUS}] + [{"CPU": worker_cpus}] * workers
    # the learner's device: cpu unless asked (auto would look at the cluster, not the group)
    if (options.device or "cpu").startswith("cuda"):
        bundles.append({"GPU": 1.0})
    return worker_cpus, bundles


def _at_once(tuning: TuneOptions) -> int:
    """Trials that run at once: ``--concurrent-trials``, all by default."""
    return min(tuning.concurrent_trials or tuning.trials, tuning.trials)


def _all_at_once(options: TrainOptions, tuning: TuneOptions) -> bool:
    """Whether every trial has its resources at once: locally ``_trial_resources`` sizes
    them so that ``_at_once`` fit; a cluster's size is the operator's."""
    return not options.address and _at_once(tuning) == tuning.trials


def _scheduler(planned: TunePlan) -> Any:
    from ray.tune.schedulers import ASHAScheduler, FIFOScheduler, PopulationBasedTraining

    from driver.tuning.pbt import AllAtOncePBT

    tuning = planned.tuning
    if tuning.scheduler == "pbt":
        interval = tuning.perturbation_interval or max(planned.report_every, planned.max_steps // 5)
        pbt = AllAtOncePBT if _all_at_once(planned.options, tuning) else PopulationBasedTraining
        return pbt(
            time_attr="steps",
            perturbation_interval=interval,
            quantile_fraction=tuning.quantile_fraction,
            hyperparam_mutations=planned.search.mutations(),
        )
    if tuning.scheduler == "asha":
        return ASHAScheduler(
            time_attr="steps",
            max_t=planned.max_steps,
            grace_period=min(planned.max_steps, 2 * planned.report_every),
        )
    return FIFOScheduler()


def _write_results(planned: TunePlan, results: Any) -> TuneResult:
    """trials.csv and best.yaml, where the run's directory is."""
    keys = [d.key for d in planned.search.dimensions]
    rows = []
    for result in results:
        metrics = result.metrics or {}
        config = result.config or {}
        rows.append(
            {
                "trial": metrics.get("trial_id", Path(result.path).name),
                **{key: config.get(key) for key in keys},
                "steps": metrics.get("steps"),
                "reward": metrics.get("reward"),
                "error": "" if result.error is None else str(result.error).splitlines()[0],
                "run_dir": metrics.get("run_dir", ""),
            }
        )
    planned.root.mkdir(parents=True, exist_ok=True)
    with open(planned.root / "trials.csv", "w", newline="") as file:
        writer = csv.DictWriter(
            file, fieldnames=["trial", *keys, "steps", "reward", "error", "run_dir"]
        )
        writer.writeheader()
        writer.writerows(rows)
    ranked = [r for r in rows if isinstance(r["reward"], float) and math.isfinite(r["reward"])]
    errors = sum(1 for r in rows if r["error"])
    if not ranked:
        return TuneResult(planned.root, len(rows), errors, None, None, None)
    best = max(ranked, key=lambda r: r["reward"])
    best_path = planned.root / "best.yaml"
    data = with_values(planned.config_data, {key: best[key] for key in keys})
    header = (
        f"# the best of {len(rows)} trials: {best['trial']}, mean reward {best['reward']:.4f} "
        f"at {best['steps']} steps ({best['run_dir']})\n"
    )
    best_path.write_text(header + yaml.safe_dump(data, sort_keys=False))
    return TuneResult(planned.root, len(rows), errors, best["trial"], best["reward"], best_path)
