"""One Tune trial: a full run of its own (its workers, its learner, its checkpoints, its
summaries) in ``<results>/<run id>/trials/<trial id>/``, driven in slices of
``report_every`` steps by Tune's class API.

Tune's ``save_checkpoint`` and ``load_checkpoint`` are the run's own checkpoint files (the
learner's optimizer and normalizer state, step counts and weights version included), so
PBT's exploit is a resume from another trial's checkpoint with this trial's new config.
Each stretch of a trial between two loads ends as a run ends (``TrainingRun.finish``): a
final checkpoint, every process stopped, its ``summary.json`` with the sample ledger, kept
as ``pieces/<n>.json``. Every actor of a trial lives in the trial's placement group, and
its Unity instances take their ports from the node's registry, as any run's do."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from ray import tune

from batches.contracts import base_name
from driver.options import TrainOptions
from driver.system import unity_config
from driver.training.checkpoints import Checkpoints
from driver.training.curriculum import lesson_plan
from driver.training.planner import Start, check_fits, open_run, plan
from driver.training.run import Progress, TrainingRun
from driver.tuning.search import with_values

log = logging.getLogger(__name__)
CHECKPOINT_FOLDER = "run"  # inside Tune's checkpoint directory: a run's checkpoints/ layout


@dataclass(frozen=True)
class TrialBase:
    """What every trial shares: the run's options and trainer config, where trials live,
    which behavior ranks them and how often they report."""

    options: TrainOptions
    config_data: dict[str, Any]
    root: Path  # <results>/<run id>
    metric_behavior: str
    report_every: int
    worker_cpus: float

    @property
    def trials_dir(self) -> Path:
        return self.root / "trials"


def total_steps(progress: Progress) -> int:
    return sum(int(s) for s in progress["steps"].values())


class UnityTrial(tune.Trainable):
    def setup(self, config: dict[str, Any], base: TrialBase) -> None:
        self.base, self.values = base, dict(config)
        self.run: TrainingRun | None = None
        self.restored: dict[str, Any] | None = None  # a checkpoint's state, for the next open
        self.reported_at = 0

    # --- Tune's API -------------------------------------------------------------------

    def step(self) -> dict[str, Any]:
        run = self.run or self._open()
        target = self.reported_at + self.base.report_every
        try:
            progress = run.advance(stop=lambda p: total_steps(p) >= target)
        except BaseException:
            self._close(failed=True)
            raise
        self.reported_at = max(target, total_steps(progress))
        return self._result(run, progress)

    def save_checkpoint(self, checkpoint_dir: str) -> None:
        folder = Path(checkpoint_dir) / CHECKPOINT_FOLDER
        if self.run is not None:
            self.run.save(Checkpoints(folder, self.run.config, {}))
        elif self.restored is not None:  # restored, not yet run again: what it holds
            shutil.copytree(self._stash, folder / "checkpoints")

    def load_checkpoint(self, checkpoint_dir: str) -> None:
        """Another trial's checkpoint (PBT's exploit) or this one's (a paused trial
        resumed), kept in the trial's folder (Tune may delete its copy once this returns)
        and said in its ``restores.jsonl``: from which trial, at which step, with which
        values."""
        from learners.host import checkpoint

        self._close()
        shutil.rmtree(self._stash, ignore_errors=True)
        shutil.copytree(Path(checkpoint_dir) / CHECKPOINT_FOLDER / "checkpoints", self._stash)
        self.restored = checkpoint.load(self._stash)
        self.reported_at = int(self.restored["step"])
        record = {"from": self.restored["meta"].get("run_id"), "step": self.reported_at}
        with open(self._stash.parent / "restores.jsonl", "a") as file:
            file.write(json.dumps({**record, "config": self.values}) + "\n")

    def cleanup(self) -> None:
        self._close()

    # --- the run ------------------------------------------------------------------------

    @property
    def _stash(self) -> Path:
        return self.base.trials_dir / self.trial_id / "restored"

    @property
    def number(self) -> int:
        """The trial's index in the search (Tune's trial ids end in it): its seed's offset."""
        return int(self.trial_id.rsplit("_", 1)[-1])

    def _open(self) -> TrainingRun:
        base = self.base
        run_dir = base.trials_dir / self.trial_id
        run_dir.mkdir(parents=True, exist_ok=True)
        config_path = run_dir / "trainer_config.yaml"
        data = with_values(base.config_data, self.values)
        config_path.write_text(yaml.safe_dump(data, sort_keys=False))
        options = dataclasses.replace(
            base.options,
            config=str(config_path),
            run_id=self.trial_id,
            results_dir=str(base.trials_dir),
            seed=base.options.seed + self.number,
            force=True,  # a later stretch of this trial: it goes on in the same folder
            progress=False,
            given=base.options.given | {"config", "run_id", "results_dir", "seed", "force"},
        )
        planned = plan(options)
        start = open_run(planned)
        if self.restored is not None:
            check_fits(self.restored, planned.config, options.seed, run_dir, "PBT's exploit")
            start = Start(resume=self.restored)
        lessons = lesson_plan(planned.options, planned.config, start.resume)
        unity = unity_config(planned.options, planned.config, run_dir, lessons)
        run = TrainingRun(
            planned.options,
            planned.config,
            unity,
            run_dir,
            start,
            lessons,
            planned.experts,
            base.worker_cpus,
        )
        self.run = run.__enter__()
        self.reported_at = sum(run.start_steps.values())
        return run

    def _close(self, failed: bool = False) -> None:
        """The run's stretch ends as a run ends; its summary kept as the next piece."""
        run, self.run = self.run, None
        if run is None:
            return
        if failed:
            run.__exit__(None, None, None)
            return
        try:
            run.finish()
        finally:
            run.__exit__(None, None, None)
        pieces = run.run_dir / "pieces"
        pieces.mkdir(exist_ok=True)
        number = len(list(pieces.glob("*.json"))) + 1
        shutil.copy(run.run_dir / "summary.json", pieces / f"{number}.json")

    def _result(self, run: TrainingRun, progress: Progress) -> dict[str, Any]:
        """What Tune ranks and schedules by: the ranked behavior's mean reward over its
        last summary (lowest possible until an episode ends), the run's steps."""
        latest = run.summaries.latest()
        rewards = {base_name(b): v["mean_reward"] for b, v in latest.items()}
        reward = rewards.get(self.base.metric_behavior)
        return {
            "reward": float("-inf") if reward is None else float(reward),
            "steps": total_steps(progress),
            "version": int(progress["version"]),
            "rewards": {b: r for b, r in rewards.items() if r is not None},
            "run_dir": str(run.run_dir),
            "done": run.over,
        }
