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
import random
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from batches.contracts import base_name
from batches.expert_steps import ExpertSteps
from driver.declaration import TrainingError, from_settings
from driver.options import TrainOptions, build_of
from learners.acting.factory import policy_factory
from learners.trainer_config.parse import (
    DEFAULTS,
    ConfigError,
    config_for_env,
    load_config,
    parse_config,
)
from learners.trainer_config.settings import RunConfig, TrainerSettings
from rollout.environment.builds import UNITYSIM_PREFIX, UnityError, resolve_build
from rollout.environment.ports import RANGE_VARIABLE, REGISTRY_VARIABLE, PortError, PortRange

log = logging.getLogger(__name__)
SQUASHING = ("tanh_squash", "conditional_sigma")  # set by the trainer type, not config keys
ACTING_ONLY = ("deterministic",)  # how a network acts, not what it is: free on a resume


@dataclass(frozen=True)
class Plan:
    options: TrainOptions
    config: RunConfig
    run_dir: Path
    resume: bool  # from the run's checkpoints
    start: Start | None = None  # the run opened (``open_run``), when it was before Ray
    # behavioral_cloning's and gail's demonstrations, by demo_path: read once, here
    experts: Mapping[str, ExpertSteps] = field(default_factory=dict)

    @property
    def loads_checkpoints(self) -> bool:
        """Whether opening the run reads checkpoints (torch), to check them against the
        config: the command line does that before it starts Ray, so a mismatch is one
        line before anything runs."""
        return self.resume or self.options.initialize_from is not None or self.init_paths

    @property
    def init_paths(self) -> bool:
        """Whether a behavior of the config starts from a checkpoint (``init_path``)."""
        return any(s.init_path for s in self.config.behaviors.values())


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
    """Everything that can be checked before Ray starts, with the trainer config's
    run-level settings taken where the command line gave none; raises TrainingError."""
    options.validate()
    check_environment()
    config = load_run_config(options)
    options = settle(from_settings(options, config.run_settings, config.source).validate())
    if options.deterministic:
        config = config.deterministic()
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
    return Plan(options, config, run_dir, resume, experts=read_experts(config))


def demonstrations_of(settings: TrainerSettings) -> dict[str, str]:
    """Each section of a behavior's settings that reads demonstrations, and its
    ``demo_path``: ``behavioral_cloning``, ``reward_signals.gail``."""
    sections = {"behavioral_cloning": settings.behavioral_cloning}
    sections |= {f"reward_signals.{s.kind}": s for s in settings.reward_signals}
    return {key: path for key, s in sections.items() if (path := getattr(s, "demo_path", None))}


def read_experts(config: RunConfig) -> dict[str, ExpertSteps]:
    """The demonstrations of every section that reads some, by ``demo_path``; a file that
    is missing, truncated or corrupt is one line naming it (its spec is checked against
    the behavior's when a worker first meets the behavior). A run without any does not
    import ``demonstrations``."""
    wanted: dict[str, str] = {}  # demo_path -> the first key that names it
    for name, settings in (*config.behaviors.items(), ("default_settings", config.default)):
        where = name if name == "default_settings" else f"behaviors.{name}"
        for section, path in demonstrations_of(settings).items():
            wanted.setdefault(path, f"{where}.{section}")
    if not wanted:
        return {}
    from demonstrations import DemoError, expert_steps

    experts: dict[str, ExpertSteps] = {}
    for path, key in wanted.items():
        try:
            experts[path] = expert_steps(path)
        except DemoError as error:
            raise TrainingError(f"{key}.demo_path: {error}") from None
    return experts


def settle(options: TrainOptions) -> TrainOptions:
    """What mlagents-learn makes of its own options: a seed of -1 drawn, --resume over
    --initialize-from, and a word for the deprecated and removed ones."""
    for name in ("torch", "tensorflow"):
        if getattr(options, name):
            log.warning("--%s was removed from mlagents-learn and does nothing here", name)
    if options.train:
        log.warning("--train is deprecated in mlagents-learn: training is the default")
    if options.resume and options.initialize_from:
        log.warning("--resume and --initialize-from: the run resumes, ignoring the initialization")
        options = replace(options, initialize_from=None)
    if options.seed == -1:
        options = replace(options, seed=random.randrange(10_000))  # as mlagents-learn draws it
        log.warning("--seed -1: this run's seed is %d", options.seed)
    return options


def _resolve(build: str | None) -> None:
    try:
        resolve_build(build)
    except UnityError as error:
        raise TrainingError(str(error)) from None


@dataclass(frozen=True)
class Start:
    """What the learner starts from: a checkpoint of this run (``--resume``), or the
    networks of another (``--initialize-from``), or neither."""

    resume: dict[str, Any] | None = None
    initial: dict[str, Any] | None = None


def open_run(plan: Plan) -> Start:
    """The checkpoints the run starts from, checked against the config, then the run's
    directory written: nothing of the run changes when a check fails."""
    options, run_dir = plan.options, plan.run_dir
    start = Start()
    if plan.resume:
        start = Start(resume=_checkpoints("--resume", run_dir, plan))
    elif options.initialize_from or plan.init_paths:
        source, initial = None, None
        if options.initialize_from:
            source = Path(options.results_dir) / options.initialize_from
            initial = _checkpoints("--initialize-from", source, plan)
        start = Start(initial=_with_init_paths(initial, source, plan))
    _resolve(build_of(options.env))
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
    record = {"options": _plain(options), "config": _plain(plan.config)}
    (run_dir / "configuration.yaml").write_text(yaml.safe_dump(record, sort_keys=False))
    return start


def _checkpoints(option: str, run_dir: Path, plan: Plan) -> dict[str, Any]:
    """A run's newest checkpoints, fit for the config; a one-line error naming the option
    when there are none or they do not fit."""
    from learners.host import checkpoint  # torch: only a driver that loads or saves one needs it

    try:
        state = checkpoint.load(run_dir)
    except checkpoint.CheckpointError as error:
        raise TrainingError(f"{option}: {error}") from None
    except FileNotFoundError:
        raise TrainingError(f"{option}: no checkpoint in {run_dir}/checkpoints") from None
    check_fits(state, plan.config, plan.options.seed, run_dir, option)
    return state


def _with_init_paths(
    initial: dict[str, Any] | None, source: Path | None, plan: Plan
) -> dict[str, Any]:
    """``initial`` (``--initialize-from``'s networks) with each ``init_path`` behavior's
    own, as mlagents-learn: a checkpoint file or folder (a run's, or one behavior's), a
    bare file name meaning that behavior's file in the ``--initialize-from`` run."""
    from learners.host import checkpoint

    behaviors = dict(initial["behaviors"]) if initial else {}
    for name, settings in plan.config.behaviors.items():
        if settings.init_path is None:
            continue
        where, path = f"behaviors.{name}.init_path", Path(settings.init_path)
        if source is not None and len(path.parts) == 1:
            found = sorted((source / "checkpoints").glob(f"{name}_team*/{path}"))
            path = found[0] if found else source / "checkpoints" / name / path
        try:
            state = checkpoint.load(path)
        except checkpoint.CheckpointError as error:
            raise TrainingError(f"{where}: {error}") from None
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            raise TrainingError(f"{where}: no checkpoint at {path}") from None
        own = {b: e for b, e in state["behaviors"].items() if base_name(b) == name}
        if not own:
            held = ", ".join(sorted(state["behaviors"])) or "nothing"
            raise TrainingError(f"{where}: {path} holds no {name} checkpoint (it holds {held})")
        behaviors.update(own)
        check_fits({"behaviors": own}, plan.config, plan.options.seed, path.parent, where)
    return {**(initial or {"version": 0}), "behaviors": behaviors}


def check_fits(
    state: dict[str, Any], config: RunConfig, seed: int, run_dir: Path, option: str = "--resume"
) -> None:
    """Each checkpointed behavior's trainer type and network are what the config builds
    now; the first difference is the error."""
    factory = policy_factory(config, seed)
    advice = (
        f"use the config it was trained with ({run_dir / 'configuration.yaml'}), or start "
        "a new --run-id"
    )
    for behavior, entry in state["behaviors"].items():
        name, now = base_name(behavior), config.for_behavior(behavior).trainer_type
        trained = entry["trainer_type"]
        if trained != now:
            raise TrainingError(
                f"{option}: {name} was trained with trainer_type {trained}, the config now "
                f"says {now}; {advice}"
            )
        wanted = dataclasses.asdict(factory.settings_for(behavior))
        for key, was in entry["network_settings"].items():
            if wanted.get(key) == was or key in ACTING_ONLY:
                continue
            if key == "memory":  # only the size shapes the weights
                sizes = [m and m["memory_size"] for m in (was, wanted.get(key))]
                if sizes[0] == sizes[1]:
                    continue
                raise TrainingError(
                    f"{option}: {name} was trained with network_settings.memory.memory_size "
                    f"{sizes[0] or 'none (no memory)'}, the config now gives "
                    f"{sizes[1] or 'none (no memory)'}; {advice}"
                )
            if key in SQUASHING:
                was_text = "a tanh-squashed (sac) policy" if was else "an unsquashed policy"
                raise TrainingError(
                    f"{option}: {name} was trained as {was_text}, the config now gives "
                    f"trainer_type {now}; {advice}"
                )
            raise TrainingError(
                f"{option}: {name} was trained with network_settings.{key} {was}, the config "
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
    if isinstance(value, frozenset | set):
        return sorted(_plain(v) for v in value)
    return value
