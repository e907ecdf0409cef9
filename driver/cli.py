"""The ``unity-rollout`` command line: each sub-command's options, checks and output; the
systems it runs are wired in ``driver/system.py``.

Each sub-command is a small function taking parsed arguments; heavy imports happen inside
the command so ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, NoReturn

from driver.declaration import TrainingError, add_arguments, from_arguments
from driver.options import (
    CollectOptions,
    RecordDemoOptions,
    TrainOptions,
    TuneOptions,
    build_of,
)

if TYPE_CHECKING:
    from driver.local_ray import BackgroundRay
    from driver.training.planner import Plan

Command = Callable[[argparse.Namespace], int]


def _error(message: object) -> int:
    """A problem the user can fix: one line, exit status 2."""
    print(f"error: {message}", file=sys.stderr)
    return 2


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
    import logging

    from driver.training.planner import open_run, plan

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("driver.training.curriculum").setLevel(
        logging.INFO
    )  # lessons, as mlagents-learn
    try:
        planned = plan(from_arguments(TrainOptions, args))  # needs neither Ray nor torch
        if planned.loads_checkpoints:  # torch, to check them against the config
            planned = dataclasses.replace(planned, start=open_run(planned))
    except TrainingError as error:
        return _error(error)
    options = dataclasses.replace(
        planned.options, progress=planned.options.progress and sys.stdout.isatty()
    )
    planned = dataclasses.replace(planned, options=options)
    if not options.address:
        _loopback_only_ray()
    from driver.local_ray import BackgroundRay

    # Ray comes up while the imports below (torch and friends) load.
    starting = None if options.address else BackgroundRay(options.cpus, options.dashboard)
    try:
        code, message = _train(options, starting, planned)
    finally:
        if starting is not None:
            starting.shutdown()
    print(message, file=sys.stderr)  # after Ray's own lines: the last line says how it ended
    return code


def _train(options: TrainOptions, starting: BackgroundRay | None, planned: Plan) -> tuple[int, str]:
    import logging

    from driver.local_ray import RayStartError
    from driver.training.train import train
    from rollout.serving.service import RolloutError

    if options.debug:  # ours, not every library's
        for package in ("driver", "rollout", "learners"):
            logging.getLogger(package).setLevel(logging.DEBUG)
    try:
        result = train(options, starting, planned)
    except TrainingError as error:
        return 2, f"error: {error}"
    except (RolloutError, RayStartError) as error:
        return 1, f"error: {error}"
    rewards = ", ".join(
        f"{name}: {v['mean_reward']:.3f}"
        for name, v in result.latest.items()
        if v.get("mean_reward") is not None
    )
    how = f"stopped by {'SIGINT/SIGTERM'}" if result.interrupted else "finished"
    return 0, (
        f"{how}: {sum(result.steps.values()):,} steps in {result.seconds:.0f}s, "
        f"mean reward {rewards or '-'}; "
        + (f"checkpoints in {result.checkpoint}" if not options.inference else "no checkpoint")
    )


def _loopback_only_ray() -> None:
    """Local mode: every Ray port and the dashboard bind 127.0.0.1. Ray reads this switch
    (its loopback-only mode, on by default on Windows and macOS) when it is imported."""
    if "ray" in sys.modules:
        raise RuntimeError("_loopback_only_ray() must run before ray is imported")
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")


def _cmd_collect(args: argparse.Namespace) -> int:
    """Collect with N workers into a counting learner: a pipeline check without training."""
    try:
        options = from_arguments(CollectOptions, args)
    except TrainingError as error:
        return _error(error)
    if not options.address:
        _loopback_only_ray()
    import ray
    from rich.console import Console

    from driver.local_ray import init_local_ray
    from driver.system import build_collect_system
    from rollout.environment.builds import UnityError, resolve_build

    console = Console()
    try:
        resolve_build(build_of(options.env))
    except UnityError as error:
        console.print(f"[red]error:[/red] {error}")
        return 2
    if options.address:
        ray.init(address=options.address)
    else:
        init_local_ray(options.cpus)
    try:
        service, learner = build_collect_system(options)
        with service:
            console.print(f"starting {options.workers} workers on {options.env} ...")
            service.run(until=lambda m: m.segments > 0)  # start-up is not in the budget
            deadline = time.monotonic() + options.seconds
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

    from learners.host.export import export_checkpoint

    try:
        written = export_checkpoint(args.source, args.out)
    except (OSError, ValueError, RuntimeError, KeyError, pickle.UnpicklingError) as error:
        message = (str(error).strip().splitlines() or [type(error).__name__])[0]
        print(f"error: cannot export {args.source}: {message}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    return 0


def _cmd_record_demo(args: argparse.Namespace) -> int:
    """Record a .demo file: one Unity instance, a checkpoint's policy or a unitysim expert."""
    try:
        options = from_arguments(RecordDemoOptions, args)
    except TrainingError as error:
        return _error(error)
    from driver.recording.record import record_demo
    from rollout.environment.builds import UnityError
    from rollout.environment.unity import RECOVERABLE

    try:
        recorded = record_demo(options)
    except (TrainingError, UnityError) as error:
        return _error(error)
    except KeyboardInterrupt:
        print("error: interrupted; no file written", file=sys.stderr)
        return 130
    except RECOVERABLE as error:  # the build crashed or hung mid-recording: nothing written
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        print(f"error: {options.env} failed while recording ({first}); no file written",
              file=sys.stderr)  # fmt: skip
        return 1
    print(
        f"{recorded.path}: {recorded.steps} steps of {recorded.behavior}, "
        f"{recorded.episodes} episodes, mean reward {recorded.mean_reward:.3f}"
    )
    return 0


def _cmd_tune(args: argparse.Namespace) -> int:
    """A Ray Tune search (PBT by default) over trainer-config keys, each trial a run."""
    import logging

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        tuning = from_arguments(TuneOptions, args)
        options = from_arguments(TrainOptions, args)
        from driver.tuning.tune import plan_tune

        planned = plan_tune(options, tuning)
    except TrainingError as error:
        return _error(error)
    from importlib.util import find_spec

    if find_spec("pandas") is None or find_spec("pyarrow") is None:
        return _error(
            "tune needs Ray Tune: pip install 'unity-rollout[tune]' (the image: docker "
            "build --build-arg EXTRAS=tune)"
        )
    if not options.address:
        _loopback_only_ray()
    from driver.tuning.tune import tune_run

    result = tune_run(planned)
    if result.best_trial is None:
        print(f"error: no trial reported a reward; see {result.root}/trials.csv", file=sys.stderr)
        return 1
    print(
        f"tune finished: {result.trials} trials ({result.errors} failed); best "
        f"{result.best_trial}, mean reward {result.best_reward:.3f}; its config: "
        f"{result.best_config}; all trials: {result.root}/trials.csv",
        file=sys.stderr,
    )
    return 1 if result.errors else 0


def _cmd_unitysim(args: argparse.Namespace) -> int:
    from unitysim.__main__ import main as unitysim_main

    return unitysim_main(args.unitysim_args)


class _Parser(argparse.ArgumentParser):
    """A command line it cannot parse is one line, as every other input error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="unity-rollout",
        description="Distributed rollouts for Unity ML-Agents environments on Ray.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    doctor = commands.add_parser("doctor", help="check that mlagents-envs imports here")
    doctor.set_defaults(func=_cmd_doctor)

    train = commands.add_parser(
        "train", help="train on a Unity environment (default: unitysim 3DBall, PPO, local mode)"
    )
    add_arguments(train, TrainOptions)
    train.set_defaults(func=_cmd_train)

    collect = commands.add_parser(
        "collect", help="collect with Ray workers into a counting learner (no training)"
    )
    add_arguments(collect, CollectOptions)
    collect.set_defaults(func=_cmd_collect)

    export = commands.add_parser(
        "export", help="export a checkpoint's policies to ONNX for Unity (Sentis)"
    )
    export.add_argument("source", help="a checkpoint (.pt) or a run directory")
    export.add_argument(
        "--out", help="output directory (default: <run>/exported or the checkpoint's directory)"
    )
    export.set_defaults(func=_cmd_export)

    record = commands.add_parser(
        "record-demo", help="record a .demo file (a checkpoint's policy or a unitysim expert)"
    )
    add_arguments(record, RecordDemoOptions)
    record.set_defaults(func=_cmd_record_demo)

    tune = commands.add_parser(
        "tune", help="search trainer-config keys with Ray Tune (PBT), each trial a full run"
    )
    add_arguments(tune, TrainOptions)
    add_arguments(tune, TuneOptions)
    tune.set_defaults(func=_cmd_tune)

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
