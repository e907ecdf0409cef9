"""The options of ``unity-rollout train`` and ``collect``, declared once: each is a typed
field with its default, its help and its check, and the command line, its help text, the
defaults and the validation all come from these declarations (``add_arguments``,
``from_arguments``, ``validate``). Validation runs before Ray starts, and every problem
is one line naming the option."""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar, get_args, get_type_hints

from rollout.restarts import RestartPolicy

Check = Callable[[Any], str | None]  # a problem with the value, or None


class TrainingError(Exception):
    """A one-line problem with the run's options, found before anything starts."""


@dataclass(frozen=True)
class Option:
    help: str
    parse: Callable[[str], Any] | None = None  # text -> value (default: the field's type)
    check: Check | None = None
    aliases: tuple[str, ...] = ()
    negative: str | None = None  # a True default switched off by this flag


def option(default: Any, help: str, **how: Any) -> Any:
    return field(default=default, metadata={"option": Option(help, **how)})


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


# ---- checks and parsers ---------------------------------------------------------------


def at_least(low: float) -> Check:
    def check(value: Any) -> str | None:
        return None if value is None or value >= low else f"at least {low:g}, got {value:g}"

    return check


def positive(value: Any) -> str | None:
    if value is None or (math.isfinite(value) and value > 0):
        return None
    return f"positive, got {value:g}"


def one_path_component(value: str) -> str | None:
    """A run id names one directory inside the results directory, never a path."""
    if value in ("", ".", "..") or any(c in value for c in "/\\\0"):
        return f"one directory name (no '/', not '.' or '..'), got {value!r}"
    return None


def workers_value(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number or auto, not {text!r}") from None


def workers_count(value: int | str) -> str | None:
    return None if value == "auto" else at_least(1)(value)


def device_value(text: str) -> str:
    from learners.devices import DEVICES, DeviceError, check_device

    try:
        return check_device(text)
    except DeviceError:
        raise argparse.ArgumentTypeError(f"{text!r}: use {DEVICES}") from None


# ---- the options ----------------------------------------------------------------------

ENV_HELP = "unitysim:<Env>, a build path, or 'editor'"
CPUS_HELP = "local mode: ray.init(num_cpus)"
_restarts = RestartPolicy()


@dataclass(frozen=True)
class TrainOptions:
    env: str = option("unitysim:3DBall", ENV_HELP)
    workers: int | Literal["auto"] = option(
        2,
        "Ray workers, one Unity each; auto: one per CPU of the cluster left after the "
        "learner's one, following the cluster as nodes join and leave",
        parse=workers_value,
        check=workers_count,
    )
    config: str | None = option(
        None, "ML-Agents trainer config YAML (default: config/<Env>.yaml if present)"
    )
    run_id: str = option("run", "results go to RESULTS_DIR/RUN_ID", check=one_path_component)
    results_dir: str = option("results", "where runs are kept")
    seed: int = option(0, "seeds the players and the policies' initial weights")
    resume: bool = option(False, "continue from the last checkpoint")
    resume_if_exists: bool = option(
        False,
        "continue from the last checkpoint when the run has one, else start it: for "
        "entrypoints that may run again (a RayJob's retries, a resubmitted job)",
    )
    force: bool = option(False, "overwrite an existing run")
    max_steps: int | None = option(None, "override every behavior's max_steps", check=at_least(1))
    max_seconds: float | None = option(None, "stop (with a checkpoint) after this", check=positive)
    num_areas: int = option(1, "training areas per Unity", check=at_least(1))
    cpus: int = option(2, CPUS_HELP, check=at_least(1))
    address: str | None = option(None, "join an existing Ray cluster (e.g. auto in a job)")
    dashboard: bool = option(
        False,
        "local mode: start Ray's dashboard too (127.0.0.1:8265; off by default, it "
        "delays the start by about 2 s)",
    )
    timeout_wait: int = option(
        60,
        "seconds to wait for Unity to connect, or to answer a step (as mlagents-learn)",
        check=at_least(1),
    )
    max_learner_restarts: int = option(
        3,
        "times the learner may die (OOM, GPU error, killed) and come back from the "
        "run's last checkpoint before the run stops",
        check=at_least(0),
    )
    max_workers: int | None = option(
        None,
        "with --workers auto: at most this many, and asks the cluster's autoscaler for "
        "room for them (KubeRay: nodes up to the worker group's maxReplicas)",
    )
    learner_cpus: float = option(
        1.0,
        "with --workers auto: the cluster's CPUs no worker counts on, left to the "
        "learner (0 where it runs on a head without CPUs for Ray, as on KubeRay)",
        check=at_least(0),
    )
    device: str | None = option(
        None,
        "the learner's device: auto (a GPU when the Ray cluster has one), cpu, cuda or "
        "cuda:N; default: the config's torch_settings.device, else auto. Workers act on CPU",
        parse=device_value,
        aliases=("--torch-device",),
    )
    mixed_precision: bool = option(
        False, "the learner runs its image encoders in bfloat16 autocast"
    )
    collect_ahead: int = option(
        0,
        "on-policy (PPO): steps workers may collect past what the learner's next update "
        "needs, acted by the weights that update replaces; keeps many workers busy through "
        "updates (0: they wait for the new weights, as mlagents-learn's environments do)",
        check=at_least(0),
    )
    no_graphics: bool = option(
        False,
        "start the build without graphics (Unity's -nographics): no display or GPU needed, "
        "but cameras send blank frames; off: the config's engine_settings.no_graphics, else "
        "off, as mlagents-learn",
    )
    max_lifetime_restarts: int = option(
        _restarts.max_lifetime_restarts,
        "restarts of one Unity instance in the run, -1: no limit (as mlagents-learn)",
        check=at_least(-1),
    )
    restarts_rate_limit_n: int = option(
        _restarts.rate_limit_n,
        "restarts of one Unity instance within the period, -1: no limit (as mlagents-learn)",
        check=at_least(-1),
    )
    restarts_rate_limit_period_s: float = option(
        _restarts.rate_limit_period_s, "the rate limit's period", check=positive
    )
    progress: bool = option(
        True,
        "no live display: one line per summary (also when output is not a terminal)",
        negative="--no-progress",
    )

    @property
    def restarts(self) -> RestartPolicy:
        """Of each Unity instance."""
        return RestartPolicy(
            self.max_lifetime_restarts,
            self.restarts_rate_limit_n,
            self.restarts_rate_limit_period_s,
        )

    def validate(self) -> TrainOptions:
        """Every option's own check, then the ones that take two; raises TrainingError."""
        check_fields(self)
        if self.env == "editor" and self.workers != 1:
            raise TrainingError("--env editor: there is one editor (port 5004), so use --workers 1")
        if self.max_workers is not None and (self.workers != "auto" or self.max_workers < 1):
            raise TrainingError("--max-workers: a number of at least 1, with --workers auto")
        return self


@dataclass(frozen=True)
class CollectOptions:
    env: str = option("unitysim:3DBall", ENV_HELP)
    workers: int = option(2, "Ray workers, one Unity each", check=at_least(1))
    seconds: float = option(30.0, "how long to collect, after the first segment", check=positive)
    horizon: int = option(64, "steps after which a row is cut", check=at_least(1))
    seed: int = option(0, "seeds the players")
    cpus: int = option(2, CPUS_HELP, check=at_least(1))
    address: str | None = option(None, "an existing Ray cluster (e.g. auto)")

    def validate(self) -> CollectOptions:
        check_fields(self)
        return self


# ---- the declarations at work -------------------------------------------------------

Options = TypeVar("Options", TrainOptions, CollectOptions)


def check_fields(options: Any) -> None:
    for item in dataclasses.fields(options):
        declared: Option = item.metadata["option"]
        if declared.check and (problem := declared.check(getattr(options, item.name))):
            raise TrainingError(f"{flag(item.name)}: {problem}")


def _scalar(annotation: Any) -> type:
    """int for ``int | None``; str for anything the command line cannot type better."""
    first = (get_args(annotation) or (annotation,))[0]
    return first if first in (bool, int, float) else str


def add_arguments(parser: argparse.ArgumentParser, kind: type) -> None:
    hints = get_type_hints(kind)
    for item in dataclasses.fields(kind):
        declared: Option = item.metadata["option"]
        default, help = item.default, declared.help
        if declared.negative:
            parser.add_argument(declared.negative, dest=item.name, action="store_false", help=help)
            continue
        scalar = _scalar(hints[item.name])
        names = (flag(item.name), *declared.aliases)
        if scalar is bool:
            parser.add_argument(*names, dest=item.name, action="store_true", help=help)
            continue
        if default is not None:
            help = f"{help} (default: {default})"
        parse = declared.parse or scalar
        parser.add_argument(*names, dest=item.name, type=parse, default=default, help=help)


def from_arguments(kind: type[Options], arguments: argparse.Namespace) -> Options:
    """The options a command line gave, checked (TrainingError on the first problem)."""
    values = {item.name: getattr(arguments, item.name) for item in dataclasses.fields(kind)}
    return kind(**values).validate()
