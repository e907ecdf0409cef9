"""Each behavior's checkpoints, as ML-Agents' trainers keep theirs: every
``checkpoint_interval`` of the behavior's own steps, in ``checkpoints/<behavior>/``, the
newest ``keep_checkpoints`` of them kept; and all of them when the run ends. A file holds
one behavior's network and algorithm state with the run's weights version
(``learners/host/checkpoint.py``); resuming takes each behavior's newest.

The driver loads torch (``learners.host.checkpoint``) only when it first saves."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from driver.training.summaries import behavior_folder, next_multiple
from learners.trainer_config.settings import RunConfig


class Checkpoints:
    def __init__(
        self, run_dir: Path, config: RunConfig, start: Mapping[str, int], writes: bool = True
    ) -> None:
        """``start``: each behavior's steps when the run (or its resumption) began;
        ``writes``: False for a run that trains nothing (``--inference``)."""
        self.directory = run_dir / "checkpoints"
        self.config, self.writes = config, writes
        for stale in self.directory.glob("*/.*.tmp"):  # a save its process was killed in
            stale.unlink(missing_ok=True)
        self.next_step = {
            behavior: next_multiple(steps, self._interval(behavior))
            for behavior, steps in start.items()
        }

    def _interval(self, behavior: str) -> int:
        return self.config.for_behavior(behavior).checkpoint_interval

    def due(self, steps: Mapping[str, int]) -> list[str]:
        """The behaviors whose steps reached their next checkpoint."""
        if not self.writes:
            return []
        return [
            behavior
            for behavior, count in steps.items()
            if count >= self.next_step.setdefault(behavior, self._interval(behavior))
        ]

    def save(self, state: dict[str, Any], meta: dict[str, Any]) -> list[Path]:
        """One file per behavior in ``state`` (a learner's ``state_dict``, whole or some
        behaviors of it), each behavior's oldest beyond its ``keep_checkpoints`` removed."""
        from learners.host import checkpoint

        saved: list[Path] = []
        if not self.writes:
            return saved
        for behavior, entry in state["behaviors"].items():
            settings = self.config.for_behavior(behavior)
            steps = int(entry["steps"])
            folder = self.directory / behavior_folder(behavior)
            one = {"step": steps, "version": state["version"], "behaviors": {behavior: entry}}
            for key in ("behavior_keys", "self_play"):  # run-wide: in every behavior's file
                if state.get(key) is not None:
                    one[key] = state[key]
            saved.append(checkpoint.save(folder / f"step-{steps:010d}.pt", {**one, "meta": meta}))
            self.next_step[behavior] = next_multiple(steps, settings.checkpoint_interval)
            for old in checkpoint.newest_first(folder)[settings.keep_checkpoints :]:
                old.unlink(missing_ok=True)
        return saved
