"""The ``unity-rollout`` command line: the one place that wires the parts together.

Each sub-command is a small function taking parsed arguments; heavy imports happen inside
the command so ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from rollout.restarts import RestartPolicy

if TYPE_CHECKING:
    from driver.local_ray import BackgroundRay

Command = Callable[[argparse.Namespace], int]


def _positive_seconds(text: str) -> float:
    """argparse type: a bad value is argparse's one-line error, before Ray starts."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number of seconds, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"positive, got {value:g}")
    return value


def _cmd_doctor(args: argparse.Namespace) -> int:
    """Show which compatibility fixes this interpreter needs and the key package versions."""
    import platform
    from importlib import metadata

    import mlagents_compat as compat

    fixes = compat.install()
    import mlagents_envs.environment  # noqa: F401  (proves the import works)
    from google.protobuf.internal import api_implementation

    print(f"python            {platform.python_version()}")
    for dist in ("mlagents-envs", "protobuf", "grpcio", "numpy", "torch", "torchrl", "ray"):
        try:
            version = metadata.version(dist)
        except metadata.PackageNotFoundError:
            version = "not installed"
        print(f"{dist:<17} {version}")
    print(f"protobuf backend  {api_implementation.Type()}")
    print(f"compat fixes      {', '.join(fixes) or 'none needed'}")
    from unitysim.envs.ball3d import compiled_physics

    physics = "C" if compiled_physics() else "numpy (no C build, or UNITYSIM_PHYSICS=numpy)"
    print(f"3DBall physics    {physics}")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    """Train with the central learner (PPO, SAC or IMPALA per the trainer config)."""
    if not args.address:
        _loopback_only_ray()
    from driver.local_ray import BackgroundRay

    # Ray comes up while the imports below (torch and friends) load.
    starting = None if args.address else BackgroundRay(args.cpus, args.dashboard)
    try:
        return _train(args, starting)
    finally:
        if starting is not None:
            starting.shutdown()


def _train(args: argparse.Namespace, starting: BackgroundRay | None) -> int:
    import logging

    from rich.console import Console

    from driver.train import TrainingError, TrainOptions, train
    from rollout.service import RolloutError

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    console = Console(stderr=True)
    restarts = RestartPolicy(
        max_lifetime_restarts=args.max_lifetime_restarts,
        rate_limit_n=args.restarts_rate_limit_n,
        rate_limit_period_s=args.restarts_rate_limit_period_s,
    )
    options = TrainOptions(
        env=args.env,
        workers=args.workers,
        config=args.config,
        run_id=args.run_id,
        results_dir=args.results_dir,
        seed=args.seed,
        resume=args.resume,
        resume_if_exists=args.resume_if_exists,
        force=args.force,
        max_steps=args.max_steps,
        max_seconds=args.max_seconds,
        cpus=args.cpus,
        address=args.address,
        progress=not args.no_progress and sys.stdout.isatty(),
        num_areas=args.num_areas,
        restarts=restarts,
        timeout_wait=args.timeout_wait,
        max_learner_restarts=args.max_learner_restarts,
        collect_ahead=args.collect_ahead,
        max_workers=args.max_workers,
        learner_cpus=args.learner_cpus,
        device=args.device,
        mixed_precision=args.mixed_precision,
    )
    try:
        result = train(options, starting)
    except TrainingError as error:
        console.print(f"[red]error:[/red] {error}", soft_wrap=True)
        return 2
    except RolloutError as error:
        console.print(f"[red]error:[/red] {error} (a checkpoint was kept)", soft_wrap=True)
        return 1
    rewards = ", ".join(
        f"{name}: {v['mean_reward']:.3f}"
        for name, v in result.latest.items()
        if v.get("mean_reward") is not None
    )
    how = f"stopped by {'SIGINT/SIGTERM'}" if result.interrupted else "finished"
    console.print(
        f"{how}: {sum(result.steps.values()):,} steps in {result.seconds:.0f}s, "
        f"mean reward {rewards or '-'}; checkpoint {result.checkpoint}",
        soft_wrap=True,
    )
    return 0


def _loopback_only_ray() -> None:
    """Local mode: every Ray port and the dashboard bind 127.0.0.1. Ray reads this switch
    (its loopback-only mode, on by default on Windows and macOS) when it is imported."""
    if "ray" in sys.modules:
        raise RuntimeError("_loopback_only_ray() must run before ray is imported")
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")


def _device(value: str) -> str:
    from learners.devices import DEVICES, DeviceError, check_device

    try:
        return check_device(value)
    except DeviceError:
        raise argparse.ArgumentTypeError(f"{value!r}: use {DEVICES}") from None


def _workers(value: str) -> int | str:
    if value == "auto":
        return value
    try:
        return int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number or auto, not {value!r}") from None


def _cmd_collect(args: argparse.Namespace) -> int:
    """Collect with N workers into a counting learner: a pipeline check without training."""
    if not args.address:
        _loopback_only_ray()
    import ray
    from rich.console import Console

    from driver.counting_learner import CountingLearner
    from driver.local_ray import init_local_ray
    from learners.factory import actor_factory
    from rollout.service import RolloutService, ServiceConfig
    from rollout.unity import UnityConfig, UnityError, resolve_build

    console = Console()
    build = None if args.env == "editor" else args.env
    try:
        resolve_build(build)
    except UnityError as error:
        console.print(f"[red]error:[/red] {error}")
        return 2
    if args.address:
        ray.init(address=args.address)
    else:
        init_local_ray(args.cpus)
    try:
        learner = ray.remote(CountingLearner).options(num_cpus=0).remote()
        config = ServiceConfig(
            UnityConfig(build, seed=args.seed),
            num_workers=args.workers,
            horizon=args.horizon,
            worker_cpus=min(1.0, args.cpus / args.workers) if not args.address else 1.0,
        )
        with RolloutService(config, actor_factory, learner) as service:
            console.print(f"starting {args.workers} workers on {args.env} ...")
            service.run(until=lambda m: m.segments > 0)  # start-up is not in the budget
            deadline = time.monotonic() + args.seconds
            while time.monotonic() < deadline:
                metrics = service.run(seconds=min(5.0, deadline - time.monotonic()))
                rate = metrics.agent_steps / max(metrics.seconds, 1e-9)
                returns = ", ".join(
                    f"{name}: {mean:.2f}" for name, mean in metrics.mean_returns().items()
                )
                console.print(
                    f"{metrics.seconds:6.1f}s  agent steps {metrics.agent_steps:>8}  "
                    f"({rate:,.0f}/s)  lag {metrics.policy_lag_mean:.2f}  "
                    f"restarts {metrics.unity_restarts}  returns {returns or '-'}"
                )
        console.print(ray.get(learner.summary.remote()))
    finally:
        ray.shutdown()
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    """Export a checkpoint's policies to ONNX files for Unity (one per behavior)."""
    import pickle

    from learners.export import export_checkpoint

    try:
        written = export_checkpoint(args.source, args.out)
    except (OSError, ValueError, RuntimeError, KeyError, pickle.UnpicklingError) as error:
        message = (str(error).strip().splitlines() or [type(error).__name__])[0]
        print(f"error: cannot export {args.source}: {message}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    return 0


def _cmd_unitysim(args: argparse.Namespace) -> int:
    from unitysim.__main__ import main as unitysim_main

    return unitysim_main(args.unitysim_args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="unity-rollout",
        description="Distributed rollouts for Unity ML-Agents environments on Ray.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    doctor = commands.add_parser("doctor", help="check that mlagents-envs imports here")
    doctor.set_defaults(func=_cmd_doctor)

    train = commands.add_parser(
        "train", help="train on a Unity environment (default: unitysim 3DBall, PPO, local mode)"
    )
    train.add_argument(
        "--env", default="unitysim:3DBall", help="unitysim:<Env>, a build path, or 'editor'"
    )
    train.add_argument(
        "--workers",
        type=_workers,
        default=2,
        help="Ray workers, one Unity each; auto: one per CPU of the cluster left after the "
        "learner's one, following the cluster as nodes join and leave",
    )
    train.add_argument(
        "--config", help="ML-Agents trainer config YAML (default: config/<Env>.yaml if present)"
    )
    train.add_argument("--run-id", default="run", help="results go to RESULTS_DIR/RUN_ID")
    train.add_argument("--results-dir", default="results")
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--resume", action="store_true", help="continue from the last checkpoint")
    train.add_argument(
        "--resume-if-exists",
        action="store_true",
        help="continue from the last checkpoint when the run has one, else start it: for "
        "entrypoints that may run again (a RayJob's retries, a resubmitted job)",
    )
    train.add_argument("--force", action="store_true", help="overwrite an existing run")
    train.add_argument("--max-steps", type=int, help="override every behavior's max_steps")
    train.add_argument("--max-seconds", type=float, help="stop (with a checkpoint) after this")
    train.add_argument("--num-areas", type=int, default=1, help="training areas per Unity")
    train.add_argument("--cpus", type=int, default=2, help="local mode: ray.init(num_cpus)")
    train.add_argument("--address", help="join an existing Ray cluster (e.g. auto in a job)")
    train.add_argument(
        "--dashboard",
        action="store_true",
        help="local mode: start Ray's dashboard too (127.0.0.1:8265; off by default, it "
        "delays the start by about 2 s)",
    )
    train.add_argument(
        "--timeout-wait",
        type=int,
        default=60,
        help="seconds to wait for Unity to connect, or to answer a step (as mlagents-learn)",
    )
    train.add_argument(
        "--max-learner-restarts",
        type=int,
        default=3,
        help="times the learner may die (OOM, GPU error, killed) and come back from the "
        "run's last checkpoint before the run stops",
    )
    train.add_argument(
        "--max-workers",
        type=int,
        help="with --workers auto: at most this many, and asks the cluster's autoscaler for "
        "room for them (KubeRay: nodes up to the worker group's maxReplicas)",
    )
    train.add_argument(
        "--learner-cpus",
        type=float,
        default=1.0,
        help="with --workers auto: the cluster's CPUs no worker counts on, left to the "
        "learner (0 where it runs on a head without CPUs for Ray, as on KubeRay)",
    )
    train.add_argument(
        "--device",
        "--torch-device",
        type=_device,
        help="the learner's device: auto (a GPU when the Ray cluster has one), cpu, cuda or "
        "cuda:N; default: the config's torch_settings.device, else auto. Workers act on CPU",
    )
    train.add_argument(
        "--mixed-precision",
        action="store_true",
        help="the learner runs its image encoders in bfloat16 autocast (off by default)",
    )
    train.add_argument(
        "--collect-ahead",
        type=int,
        default=0,
        help="on-policy (PPO): steps workers may collect past what the learner's next update "
        "needs, acted by the weights that update replaces; keeps many workers busy through "
        "updates (0: they wait for the new weights, as mlagents-learn's environments do)",
    )
    defaults = RestartPolicy()
    train.add_argument(
        "--max-lifetime-restarts",
        type=int,
        default=defaults.max_lifetime_restarts,
        help="restarts of one Unity instance in the run, -1: no limit (as mlagents-learn; "
        f"default {defaults.max_lifetime_restarts})",
    )
    train.add_argument(
        "--restarts-rate-limit-n",
        type=int,
        default=defaults.rate_limit_n,
        help="restarts of one Unity instance within the period, -1: no limit (as "
        f"mlagents-learn; default {defaults.rate_limit_n})",
    )
    train.add_argument(
        "--restarts-rate-limit-period-s",
        type=_positive_seconds,
        default=defaults.rate_limit_period_s,
        help=f"the rate limit's period (default {defaults.rate_limit_period_s:g})",
    )
    train.add_argument(
        "--no-progress",
        action="store_true",
        help="no live display: one line per summary (also when output is not a terminal)",
    )
    train.set_defaults(func=_cmd_train)

    collect = commands.add_parser(
        "collect", help="collect with Ray workers into a counting learner (no training)"
    )
    collect.add_argument(
        "--env", default="unitysim:3DBall", help="unitysim:<Env>, a build path, or 'editor'"
    )
    collect.add_argument("--workers", type=int, default=2)
    collect.add_argument("--seconds", type=float, default=30.0)
    collect.add_argument("--horizon", type=int, default=64)
    collect.add_argument("--seed", type=int, default=0)
    collect.add_argument("--cpus", type=int, default=2, help="local mode: ray.init(num_cpus)")
    collect.add_argument("--address", help="an existing Ray cluster (e.g. auto)")
    collect.set_defaults(func=_cmd_collect)

    export = commands.add_parser(
        "export", help="export a checkpoint's policies to ONNX for Unity (Sentis)"
    )
    export.add_argument("source", help="a checkpoint (.pt) or a run directory")
    export.add_argument(
        "--out", help="output directory (default: <run>/exported or the checkpoint's directory)"
    )
    export.set_defaults(func=_cmd_export)

    unitysim = commands.add_parser(
        "unitysim", help="the headless Unity stand-in (build, list, play, editor)"
    )
    unitysim.add_argument("unitysim_args", nargs=argparse.REMAINDER)
    unitysim.set_defaults(func=_cmd_unitysim)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    func: Command = args.func
    return func(args)


if __name__ == "__main__":
    sys.exit(main())
