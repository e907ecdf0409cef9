"""The options of ``unity-rollout train``, ``collect`` and ``record-demo``, declared once:
each is a typed field with its default, its help, its check and, for mlagents-learn's, its
key in a trainer config's run-level sections; the command line, its help text, the defaults, the
config's run-level keys and the validation all come from these declarations
(``driver/declaration.py``). Every mlagents-learn 1.1.0 option is one of them, with its
meaning; where our default differs, the help says so. Validation runs before Ray starts,
and every problem is one line naming the option."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Literal

from driver.declaration import (
    TrainingError,
    at_least,
    check_fields,
    given_field,
    one_path_component,
    option,
    positive,
)
from rollout.environment.restarts import RestartPolicy

__all__ = ["CollectOptions", "RecordDemoOptions", "TrainOptions", "TrainingError", "TuneOptions"]


def build_of(env: str) -> str | None:
    """The build an ``--env`` names; None for the Editor (its Play button)."""
    return None if env == "editor" else env


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
    from learners.host.devices import DEVICES, DeviceError, check_device

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
    env: str = option(
        "unitysim:3DBall",
        f"{ENV_HELP} (mlagents-learn's default is the editor)",
        yaml="env_settings.env_path",
    )
    config: str | None = option(
        None,
        "ML-Agents trainer config YAML, also as the first argument, as mlagents-learn takes "
        "it (default: config/<Env>.yaml if present)",
        positional="trainer_config_path",
    )
    workers: int | Literal["auto"] = option(
        2,
        "Ray workers, one Unity each (mlagents-learn's --num-envs, whose default is 1); "
        "auto: one per CPU of the cluster left after the learner's one, following the "
        "cluster as nodes join and leave",
        parse=workers_value,
        check=workers_count,
        aliases=("--num-envs",),
        yaml="env_settings.num_envs",
    )
    run_id: str = option(
        "run",
        "results go to RESULTS_DIR/RUN_ID (mlagents-learn's default: ppo)",
        check=one_path_component,
        yaml="checkpoint_settings.run_id",
    )
    results_dir: str = option(
        "results", "where runs are kept", yaml="checkpoint_settings.results_dir"
    )
    seed: int = option(
        0,
        "seeds the players and the policies' initial weights; -1: a random seed, "
        "mlagents-learn's default (ours is 0, so that a run can be repeated)",
        check=at_least(-1),
        yaml="env_settings.seed",
    )
    resume: bool = option(
        False,
        "continue from each behavior's newest checkpoint",
        aliases=("--load",),
        yaml=("checkpoint_settings.resume", "checkpoint_settings.load_model"),
    )
    resume_if_exists: bool = option(
        False,
        "continue from the last checkpoint when the run has one, else start it: for "
        "entrypoints that may run again (a RayJob's retries, a resubmitted job)",
    )
    force: bool = option(False, "overwrite an existing run", yaml="checkpoint_settings.force")
    initialize_from: str | None = option(
        None,
        "start from the networks of RUN_ID, another run in RESULTS_DIR (its steps and "
        "optimizer state are not taken); --resume wins over it",
        check=one_path_component,
        yaml="checkpoint_settings.initialize_from",
    )
    inference: bool = option(
        False,
        "run the policies without training them (with --resume or --initialize-from: the "
        "trained ones); no checkpoint is written",
        yaml="checkpoint_settings.inference",
    )
    train: bool = option(
        False,
        "mlagents-learn's deprecated --train: training is the default",
        hidden=True,
        yaml="checkpoint_settings.train_model",
    )
    max_steps: int | None = option(None, "override every behavior's max_steps", check=at_least(1))
    max_seconds: float | None = option(None, "stop (with a checkpoint) after this", check=positive)
    num_areas: int = option(
        1, "training areas per Unity", check=at_least(1), yaml="env_settings.num_areas"
    )
    base_port: int | None = option(
        None,
        "the Unity instances' ports from this one up (100 of them; a restarted instance "
        "takes a fresh one); default: UNITY_ROLLOUT_PORT_RANGE, else a free range "
        "(mlagents-learn's default: 5005)",
        check=at_least(1024),
        yaml="env_settings.base_port",
    )
    env_args: tuple[str, ...] = option(
        (),
        "every argument after it goes to the Unity executable, as with mlagents-learn",
        rest=True,
        yaml="env_settings.env_args",
    )
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
        yaml="env_settings.timeout_wait",
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
    learner_threads: int | None = option(
        None,
        "torch threads of the learner; default: every core it may use where the workers "
        "wait through its updates (PPO, POCA), else 1; OMP_NUM_THREADS where set",
        check=at_least(1),
    )
    device: str | None = option(
        None,
        "the learner's device: auto (a GPU when the Ray cluster has one), cpu, cuda or "
        "cuda:N; default: the config's torch_settings.device, else auto. Workers act on CPU",
        parse=device_value,
        aliases=("--torch-device",),
    )
    mixed_precision: bool = option(
        False,
        "the learner runs its hidden layers in bfloat16 autocast (heads in float32); float32 "
        "with a warning where bfloat16 is emulated (a CPU without AVX-512 or AMX)",
    )
    deterministic: bool = option(
        False,
        "act deterministically: the mean of continuous actions, the likeliest of discrete "
        "ones (every behavior's network_settings.deterministic)",
    )
    collect_ahead: int = option(
        0,
        "on-policy (PPO): steps workers may collect past what the learner's next update "
        "needs, acted by the weights that update replaces; keeps many workers busy through "
        "updates (0: they wait for the new weights, as mlagents-learn's environments do, "
        "unless their rows in progress hold more than a buffer; a behavior with "
        "threaded: true raises it to its buffer_size)",
        check=at_least(0),
    )
    no_graphics: bool = option(
        False,
        "start the build without graphics (Unity's -nographics): no display or GPU needed, "
        "but cameras send blank frames; off: the config's engine_settings.no_graphics, else "
        "off, as mlagents-learn",
    )
    no_graphics_monitor: bool = option(
        False,
        "the first Unity instance with graphics, the others without (engine_settings."
        "no_graphics_monitor)",
    )
    width: int | None = option(
        None, "the window's width in pixels (default: engine_settings, else 84)", check=at_least(1)
    )
    height: int | None = option(
        None, "the window's height in pixels (default: engine_settings, else 84)", check=at_least(1)
    )
    quality_level: int | None = option(
        None, "Unity's quality level (default: engine_settings, else 5)", check=at_least(0)
    )
    time_scale: float | None = option(
        None, "Unity's time scale (default: engine_settings, else 20)", check=positive
    )
    target_frame_rate: int | None = option(
        None, "Unity's target frame rate (default: engine_settings, else -1)", check=at_least(-1)
    )
    capture_frame_rate: int | None = option(
        None, "Unity's capture frame rate (default: engine_settings, else 60)", check=at_least(0)
    )
    max_lifetime_restarts: int = option(
        _restarts.max_lifetime_restarts,
        "restarts of one Unity instance in the run, -1: no limit (mlagents-learn's default: 10)",
        check=at_least(-1),
        yaml="env_settings.max_lifetime_restarts",
    )
    restarts_rate_limit_n: int = option(
        _restarts.rate_limit_n,
        "restarts of one Unity instance within the period, -1: no limit (mlagents-learn's "
        "default: 1)",
        check=at_least(-1),
        yaml="env_settings.restarts_rate_limit_n",
    )
    restarts_rate_limit_period_s: float = option(
        _restarts.rate_limit_period_s,
        "the rate limit's period",
        check=positive,
        yaml="env_settings.restarts_rate_limit_period_s",
    )
    debug: bool = option(False, "debug-level logging from the driver", yaml="debug")
    torch: bool = option(False, "removed from mlagents-learn: ignored", hidden=True)
    tensorflow: bool = option(False, "removed from mlagents-learn: ignored", hidden=True)
    progress: bool = option(
        True,
        "no live display: one line per summary (also when output is not a terminal)",
        negative="--no-progress",
    )
    given: frozenset[str] = given_field()

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
    given: frozenset[str] = given_field()

    def validate(self) -> CollectOptions:
        check_fields(self)
        return self


def demo_path(value: str | None) -> str | None:
    if value is None:
        return "required: the .demo file to write"
    return None if value.endswith(".demo") else f"a file name ending in .demo, got {value!r}"


@dataclass(frozen=True)
class RecordDemoOptions:
    env: str = option("unitysim:3DBall", f"{ENV_HELP} (one instance, on a leased port)")
    out: str | None = option(
        None, "the .demo file to write (its name is the demo's)", check=demo_path
    )
    checkpoint: str | None = option(
        None, "a checkpoint (.pt) or a run directory, as export takes it: the policies that act"
    )
    heuristic: bool = option(
        False, "unitysim builds: the environment's scripted expert plays the recorded behavior"
    )
    behavior: str | None = option(None, "the behavior to record (default: the build's only one)")
    steps: int | None = option(None, "agent steps to record (default 1000)", check=at_least(1))
    episodes: int | None = option(None, "record until this many episodes end", check=at_least(1))
    stochastic: bool = option(False, "sample the policy's actions (default: its most likely)")
    actions: Literal["unity", "decided"] = option(
        "unity",
        "the action stored with a step: unity, the one that led to it, as Unity's recorder "
        "stores it (zeros at an episode's first step); decided, the one taken at it",
        parse=lambda text: text,
        check=lambda v: None if v in ("unity", "decided") else f"unity or decided, got {v!r}",
    )
    seed: int = option(0, "seeds the player and the random actions")
    no_graphics: bool = option(False, "start the build with -nographics")
    timeout_wait: int = option(60, "seconds to wait for the build to connect", check=at_least(1))
    given: frozenset[str] = given_field()

    def validate(self) -> RecordDemoOptions:
        check_fields(self)
        if self.checkpoint is None and not self.heuristic:
            raise TrainingError("give --checkpoint PATH (a trained policy) or --heuristic")
        if self.heuristic and not self.env.startswith("unitysim:"):
            raise TrainingError(
                f"--heuristic: scripted experts exist for unitysim builds only, not {self.env!r}"
            )
        if self.steps is not None and self.episodes is not None:
            raise TrainingError("give --steps or --episodes, not both")
        return self

    @property
    def step_limit(self) -> int | None:
        return self.steps if self.steps is not None or self.episodes is not None else 1000


def search_file(value: str | None) -> str | None:
    return "required: a YAML file of trainer-config keys and values to try" if not value else None


@dataclass(frozen=True)
class TuneOptions:
    """``unity-rollout tune``'s own options; each trial takes ``train``'s (docs/tune.md)."""

    search: str | None = option(
        None, "a YAML file: trainer-config keys and the values to try", check=search_file
    )
    trials: int = option(
        4, "trials (Tune's num_samples; a grid multiplies them)", check=at_least(1)
    )
    scheduler: Literal["pbt", "asha", "fifo"] = option(
        "pbt",
        "pbt: population based training through the trials' checkpoints; asha: stop the "
        "worst early; fifo: every trial to its end",
        parse=lambda text: text,
        check=lambda v: None if v in ("pbt", "asha", "fifo") else f"pbt, asha or fifo, got {v!r}",
    )
    perturbation_interval: int | None = option(
        None, "pbt: steps between exploit and explore (default: max_steps / 5)", check=at_least(1)
    )
    quantile_fraction: float = option(
        0.25,
        "pbt: the share of trials that exploit the best ones at each perturbation (Tune's "
        "quantile_fraction)",
        check=lambda v: None if 0 < v <= 0.5 else f"in (0, 0.5], got {v:g}",
    )
    report_every: int | None = option(
        None,
        "steps between a trial's reports (default: the ranked behavior's summary_freq)",
        check=at_least(1),
    )
    metric_behavior: str | None = option(
        None, "the behavior whose mean reward ranks trials (default: the config's first)"
    )
    concurrent_trials: int | None = option(
        None, "trials run at once (default: all; each takes --workers workers)", check=at_least(1)
    )
    given: frozenset[str] = given_field()

    def validate(self) -> TuneOptions:
        check_fields(self)
        return self
