"""The run before it runs: its options, trainer config, build and directory are checked
before Ray starts (``plan``: no torch, no Ray, no Unity), and a resumed run's checkpoints
against its config before any file of the run is touched (``open_run``).

A run lives in ``<results>/<run id>/``: ``checkpoints/<behavior>/``, TensorBoard files
per behavior, ``configuration.yaml``, ``unity-logs/`` and ``summary.json``. It is never
overwritten silently (``--resume`` or ``--force``)."""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from batches.contracts import base_name
from driver.options import TrainingError, TrainOptions
from learners.config import DEFAULTS, ConfigError, config_for_env, load_config, parse_config
from learners.factory import policy_factory
from learners.settings import RunConfig
from rollout.builds import UNITYSIM_PREFIX, UnityError, resolve_build
from rollout.ports import RANGE_VARIABLE, REGISTRY_VARIABLE, PortError, PortRange

log = logging.getLogger(__name__)
SQUASHING = ("tanh_squash", "conditional_sigma")  # set by the trainer type, not config keys


@dataclass(frozen=True)
class Plan:
    options: TrainOptions
    config: RunConfig
    run_dir: Path
    resume: bool  # from the run's checkpoints


def load_run_config(options: TrainOptions) -> RunConfig:
    shipped = config_for_env(options.env.removeprefix(UNITYSIM_PREFIX))
    path = Path(options.config) if options.config else shipped
    try:
        return load_config(path) if path else parse_config({}, DEFAULTS)
    except ConfigError as error:
        raise TrainingError(str(error)) from None


def check_environment() -> None:
    """The environment variables a run reads, checked where the driver runs."""
    if text := os.environ.get(RANGE_VARIABLE):
        try:
            PortRange.parse(text)
        except PortError as error:
            raise TrainingError(f"{RANGE_VARIABLE}: {error}") from None
    if folder := os.environ.get(REGISTRY_VARIABLE):
        try:
            Path(folder).mkdir(parents=True, exist_ok=True)
            writable = os.access(folder, os.W_OK | os.X_OK)
        except OSError as error:
            problem = f"cannot create {folder} ({error.strerror})"
            raise TrainingError(f"{REGISTRY_VARIABLE}: {problem}") from None
        if not writable:
            raise TrainingError(f"{REGISTRY_VARIABLE}: {folder} is not writable for this user")


def plan(options: TrainOptions) -> Plan:
    """Everything that can be checked before Ray starts; raises TrainingError."""
    options.validate()
    check_environment()
    config = load_run_config(options)
    run_dir = Path(options.results_dir) / options.run_id
    has_checkpoints = any((run_dir / "checkpoints").rglob("*.pt"))
    if options.resume and not has_checkpoints:
        raise TrainingError(f"--resume: no checkpoint in {run_dir}/checkpoints to resume from")
    resume = options.resume or (options.resume_if_exists and has_checkpoints)
    if has_checkpoints and not resume and not options.force:
        raise TrainingError(
            f"{run_dir} already holds a run: pass --resume to continue it, --force to "
            "overwrite it, or choose another --run-id"
        )
    if options.env != "editor" and not options.env.startswith(UNITYSIM_PREFIX):
        _resolve(options.env)  # a build path; unitysim's names are checked as it is written
    return Plan(options, config, run_dir, resume)


def _resolve(build: str | None) -> None:
    try:
        resolve_build(build)
    except UnityError as error:
        raise TrainingError(str(error)) from None


def open_run(plan: Plan) -> dict[str, Any] | None:
    """The checkpoint to resume from (None for a fresh run), checked against the config,
    then the run's directory written: nothing of the run changes when a check fails."""
    options, run_dir = plan.options, plan.run_dir
    resume = None
    if plan.resume:
        from learners import checkpoint  # torch: only a resumed or saving driver loads it

        try:
            resume = checkpoint.load(run_dir)
        except checkpoint.CheckpointError as error:
            raise TrainingError(f"--resume: {error}") from None
        check_fits(resume, plan.config, options.seed, run_dir)
    _resolve(None if options.env == "editor" else options.env)
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
    for problem in plan.config.unsupported:
        log.warning("%s: not supported by unity-rollout, ignored", problem)
    record = {"options": dataclasses.asdict(options), "config": _plain(plan.config)}
    (run_dir / "configuration.yaml").write_text(yaml.safe_dump(record, sort_keys=False))
    return resume


def check_fits(state: dict[str, Any], config: RunConfig, seed: int, run_dir: Path) -> None:
    """Each checkpointed behavior's trainer type and network are what the config builds
    now; the first difference is the error."""
    factory = policy_factory(config, seed)
    advice = (
        f"resume with the config it was trained with ({run_dir / 'configuration.yaml'}), "
        "or start a new --run-id"
    )
    for behavior, entry in state["behaviors"].items():
        name, now = base_name(behavior), config.for_behavior(behavior).trainer_type
        trained = entry.get("trainer_type")
        if trained is not None and trained != now:
            raise TrainingError(
                f"--resume: {name} was trained with trainer_type {trained}, the config now "
                f"says {now}; {advice}"
            )
        wanted = dataclasses.asdict(factory.settings_for(behavior))
        for key, was in entry["network_settings"].items():
            if wanted.get(key) == was:
                continue
            if key in SQUASHING:
                was_text = "a tanh-squashed (sac) policy" if was else "an unsquashed policy"
                raise TrainingError(
                    f"--resume: {name} was trained as {was_text}, the config now gives "
                    f"trainer_type {now}; {advice}"
                )
            raise TrainingError(
                f"--resume: {name} was trained with network_settings.{key} {was}, the config "
                f"now gives {wanted.get(key)}; {advice}"
            )


def _plain(value: Any) -> Any:
    """Dataclasses, mappings and sequences as plain YAML data (for configuration.yaml)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value
