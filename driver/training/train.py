"""Training runs from the command line: ``train`` opens the run's directory, starts or
joins Ray and drives the run (``driver/training/run.py``) until every behavior reaches
``max_steps``, a time limit or a signal. SIGINT/SIGTERM finish the current turn, write a
final checkpoint and stop every process. The system itself is wired in
``driver/system.py``.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

import ray

from driver.local_ray import BackgroundRay, init_local_ray
from driver.options import TrainOptions
from driver.system import unity_config
from driver.training.curriculum import lesson_plan
from driver.training.planner import Plan, open_run, plan
from driver.training.run import TrainingRun, TrainResult

__all__ = ["TrainResult", "stop_on_signals", "train"]


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
        with (
            stop_on_signals() as received,
            TrainingRun(options, config, unity, run_dir, start, lessons, planned.experts) as run,
        ):
            run.advance(signals=received)
            return run.finish(received[0] if received else None)
    finally:
        if started_ray:
            ray.shutdown()
