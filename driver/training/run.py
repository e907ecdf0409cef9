"""One run while it trains: the loop of ``unity-rollout train`` as an object, so that the
CLI runs it to its end in one go and a Tune trial (``driver/tuning/trial.py``) runs it in
slices, reporting and checkpointing between them.

Each turn of the loop: the service runs for half a second, the learner's progress is
read, new behaviors are met (self-play teams join then), lessons move, summaries are
written, due checkpoints saved. A dead learner comes back from the newest checkpoint
(``driver/training/learner_keeper.py``); a failed rollout keeps what was learned, then raises.
``finish`` writes the final checkpoint, stops every process and writes ``summary.json``
with the sample ledger, which balances only once the service has stopped.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import ray
from ray.exceptions import RayActorError

from batches.contracts import base_name
from batches.expert_steps import ExpertSteps
from batches.specs import spec_from_dict
from driver.declaration import TrainingError
from driver.options import TrainOptions
from driver.system import build_system, choose_device, start_learner
from driver.training.behavior_notes import BehaviorNotes
from driver.training.checkpoints import Checkpoints
from driver.training.curriculum import LessonPlan
from driver.training.learner_keeper import LearnerKeeper
from driver.training.planner import Start, demonstrations_of
from driver.training.startup import first_steps, startup_times
from driver.training.summaries import Summaries
from learners.trainer_config.settings import RunConfig
from rollout.environment.unity import UnityConfig
from rollout.serving.service import LearnerDied, RolloutError, last_line

Progress = dict[str, Any]  # the learner's ``progress()``: steps per behavior, version, done


@dataclass(frozen=True)
class TrainResult:
    run_dir: Path
    steps: dict[str, int]
    version: int
    seconds: float
    checkpoint: Path
    interrupted: bool
    latest: dict[str, dict[str, float | None]]


class TrainingRun:
    """Built on ``__enter__`` (learner, workers, summaries), advanced by ``advance``,
    ended by ``finish``; leaving the ``with`` block without ``finish`` (an error) still
    stops every process."""

    def __init__(
        self,
        options: TrainOptions,
        config: RunConfig,
        unity: UnityConfig,
        run_dir: Path,
        start: Start,
        lessons: LessonPlan,
        experts: Mapping[str, ExpertSteps],
        worker_cpus: float | None = None,
    ) -> None:
        """``experts``: behavioral_cloning's and gail's demonstrations (``Plan.experts``)."""
        self.experts = experts
        self.worker_cpus = worker_cpus  # set by a Tune trial: its placement group's bundles
        self.options = options
        self.config = config
        self.unity = unity
        self.run_dir = run_dir
        self.start = start
        self.lessons = lessons
        resume = start.resume
        self.start_steps = (
            {n: int(b["steps"]) for n, b in resume["behaviors"].items()} if resume else {}
        )
        self.meta = {"env": options.env, "run_id": options.run_id, "lessons": lessons.lessons}
        self.progress: Progress = {"steps": {}, "version": 0, "done": False}
        self._stack = ExitStack()
        self._met: set[str] = set()

    def __enter__(self) -> TrainingRun:
        try:
            self._build()
        except BaseException:
            self._stack.close()
            raise
        return self

    def _build(self) -> None:
        options, config = self.options, self.config
        self.checkpoints = Checkpoints(
            self.run_dir, config, self.start_steps, writes=not options.inference
        )
        device = choose_device(options, config)
        self.service, learner = build_system(
            options, config, self.unity, self.start, self.experts, device, self.worker_cpus
        )
        self.keeper = LearnerKeeper(
            learner,
            lambda: start_learner(options, config, device, self.experts, self.start.initial),
            self.run_dir,
            options.max_learner_restarts,
        )
        self._stack.callback(self._end_learner)  # last: after the workers stopped
        self.started = time.perf_counter()
        self.deadline = self.started + options.max_seconds if options.max_seconds else None
        self.lessons.log_lessons()
        self.notes = BehaviorNotes(config, self.unity.no_graphics)
        self._stack.enter_context(self.service)
        self.summaries = self._stack.enter_context(
            Summaries(
                self.run_dir,
                config.for_behavior,
                options.progress,
                start_steps=self.start_steps,
            )
        )
        self.summaries.lessons = self.lessons.lessons  # the plan's own dict: updated in place

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self._stack.close()

    def _end_learner(self) -> None:
        """The learner ends with its run: a caller that trains again in the same Ray (a
        Tune trial's next stretch, a notebook) keeps no idle learner holding its buffer."""
        with contextlib.suppress(Exception):  # already dead: nothing to end
            ray.kill(self.keeper.learner, no_restart=True)

    @property
    def over(self) -> bool:
        """Every behavior has its steps, or the run's time is up."""
        late = self.deadline is not None and time.perf_counter() >= self.deadline
        return bool(self.progress.get("done")) or late

    def advance(
        self, stop: Callable[[Progress], bool] = lambda progress: False, signals: Sequence[str] = ()
    ) -> Progress:
        """Turns of the loop until the run is over, a signal was received, or ``stop``
        says so of the learner's progress."""
        while not signals and not self.over:
            self._turn()
            if stop(self.progress):
                break
        return self.progress

    def _turn(self) -> None:
        service, lessons = self.service, self.lessons
        try:
            metrics = service.run(seconds=0.5, report_every=0.5)
            self._check_demonstrations(set(metrics.specs) - self._met, metrics.specs)
            learner = self.keeper.learner
            self.progress = ray.get(learner.progress.remote())
            self.notes.report(metrics.specs)
            self.notes.learner(self.progress["notes"])
            if set(metrics.specs) - self._met:  # new behaviors: self-play teams join now
                self._met |= set(metrics.specs)
                learner.meet.remote(dict(metrics.specs))
            changed, reset = lessons.update(self.progress["steps"], metrics.episode_totals())
            if changed:
                service.set_environment_parameters(lessons.values(), reset)
            reports = ray.get(learner.drain_reports.remote())
            self.summaries.observe(metrics, self.progress, reports)
            if due := self.checkpoints.due(self.progress["steps"]):
                self.checkpoints.save(ray.get(learner.state_dict.remote(due)), self.meta)
        except RolloutError as error:  # keep what was learned, then report the cause
            kept = _keep_what_was_learned(self.keeper, self.checkpoints, self.meta)
            raise RolloutError(f"{error} ({kept})") from error
        except (LearnerDied, RayActorError) as error:  # only the learner's calls raise it
            self.keeper.restore(self.service, _cause(error))

    def _check_demonstrations(self, new: set[str], specs: Mapping[str, Any]) -> None:
        """A behavior's demonstrations (cloning, GAIL) against the spec it came with: a
        one-line error naming the file, whichever of driver and learner sees it first."""
        for behavior in new:
            for path in set(demonstrations_of(self.config.for_behavior(behavior)).values()):
                if problem := self.experts[path].problem_with(spec_from_dict(specs[behavior])):
                    raise TrainingError(f"the demonstrations of {base_name(behavior)}: {problem}")

    def state(self) -> dict[str, Any]:
        """The learner's whole state now (after every submission sent to it)."""
        return ray.get(self.keeper.learner.state_dict.remote())

    def save(self, checkpoints: Checkpoints | None = None) -> dict[str, Any]:
        """Every behavior's checkpoint now, in the run's folder or in ``checkpoints``."""
        state = self.state()
        (checkpoints or self.checkpoints).save(state, self.meta)
        return state

    def finish(self, interrupted: str | None = None) -> TrainResult:
        """The final checkpoint, every process stopped, then ``summary.json``."""
        state = self.save()
        # what the final checkpoint holds: the loop's last progress may predate submissions
        # still queued at the learner (its status calls do not wait for them)
        steps = {name: int(b["steps"]) for name, b in state["behaviors"].items()}
        self.summaries.last_updates(ray.get(self.keeper.learner.drain_reports.remote()), steps)
        latest = self.summaries.latest()
        startup = startup_times(first_steps(self.service), self.summaries.first_reward_at)
        self._stack.close()  # the service stopped: its ledger closed every incarnation
        result = TrainResult(
            self.run_dir,
            steps,
            int(state["version"]),
            time.perf_counter() - self.started,
            self.checkpoints.directory,
            interrupted is not None,
            latest,
        )
        self._write_summary(result, interrupted, startup)
        return result

    def _write_summary(
        self, result: TrainResult, interrupted: str | None, startup: Mapping[str, Any]
    ) -> None:
        service = self.service
        stats = self.progress.get("stats")  # segments Ray delivered twice, taken once
        duplicates = stats.duplicate_steps if stats is not None else 0
        summary = {
            "steps": sum(result.steps.values()),
            "behaviors": {
                name: {"steps": steps, **result.latest.get(name, {})}
                for name, steps in result.steps.items()
            },
            "version": result.version,
            "seconds": round(result.seconds, 1),
            "checkpoint": str(self.checkpoints.directory) if self.checkpoints.writes else None,
            "interrupted": interrupted,
            "faults": {**service.metrics.faults(), "duplicate_steps": duplicates},
            "ledger": service.ledger.summary(),
            "membership": service.membership and service.membership.summary(),
            "startup": dict(startup),
        }
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2))


def _keep_what_was_learned(
    keeper: LearnerKeeper, checkpoints: Checkpoints, meta: dict[str, Any]
) -> str:
    """A last checkpoint of a failed run, when it learned anything; what a retry finds."""
    try:
        state = ray.get(keeper.learner.state_dict.remote())
    except RayActorError:
        return "the learner died with the run: its last checkpoint stays"
    if not checkpoints.writes:
        return "--inference: no checkpoint"
    if not any(int(entry["steps"]) for entry in state["behaviors"].values()):
        return "nothing was trained and no checkpoint written: the same command starts it anew"
    checkpoints.save(state, meta)
    return "a checkpoint was kept: --resume continues from it"


def _cause(error: Exception) -> str:
    """Ray's last line without its paragraph of generic advice."""
    return last_line(error).split(" Some common causes")[0]
