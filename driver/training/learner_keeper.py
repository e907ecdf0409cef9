"""Keeping the learner alive: when its actor dies (out of memory, a GPU error, SIGKILL),
the driver starts a new one from the run's newest checkpoint, at most ``max_restarts``
times per run, and says so. The workers keep their Unity instances and weights meanwhile;
what was in flight to the dead learner is dropped and counted (``RolloutService.
replace_learner``). What the dead learner learned after that checkpoint is lost: at most
one ``checkpoint_interval`` of steps."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import ray

from rollout.serving.config import OUT_OF_MEMORY
from rollout.serving.service import RolloutError, RolloutService

log = logging.getLogger(__name__)


def load_into(learner: Any, state: dict[str, Any]) -> None:
    """A learner actor takes a checkpoint's state once it is built: its argument's tensors
    unpickled while the actor's build thread still imports torch failed in Ray with
    ``RaySystemError: 'torch'`` (a restored learner, seen once in a suite run)."""
    ray.get(learner.prepare.remote())
    ray.get(learner.load_state_dict.remote(state))


def initialize_into(learner: Any, state: dict[str, Any]) -> None:
    """A learner actor takes another run's networks (``--initialize-from``), once built
    (as ``load_into``)."""
    ray.get(learner.prepare.remote())
    ray.get(learner.initialize.remote(state))


class LearnerKeeper:
    """Holds the run's learner actor and restores it when it dies."""

    def __init__(
        self, learner: Any, start: Callable[[], Any], run_dir: Path, max_restarts: int
    ) -> None:
        self.learner = learner
        self._start = start  # a new learner actor, as the run first made it
        self._run_dir = run_dir
        self.max_restarts = max_restarts

    def restore(self, service: RolloutService, cause: str) -> Any:
        """A new learner from the newest checkpoint (or from the start, before the first
        one: the run's first networks, another run's with ``--initialize-from``), its
        version numbered past every version the dead one published, so that each worker
        takes the restored weights with its next collect."""
        if cause.startswith(OUT_OF_MEMORY):  # a new learner would fill the same buffer
            raise RolloutError(
                f"the learner {cause}; lower the behaviors' buffer_size or give the "
                "learner's node more memory (the run's last checkpoint stays)"
            )
        restart = service.metrics.learner_restarts + 1  # the service counts them
        if restart > self.max_restarts:
            raise RolloutError(
                f"the learner died {restart} times (--max-learner-restarts "
                f"{self.max_restarts}); last: {cause}"
            )
        with contextlib.suppress(Exception):
            ray.kill(self.learner, no_restart=True)
        from learners.host import checkpoint  # torch: only a driver that restores loads it

        learner = self._start()
        try:
            state = checkpoint.load(self._run_dir)
            source = ", ".join(Path(file).name for file in state["files"])
        except FileNotFoundError:  # died before the first checkpoint: start over
            source, state = "the start", ray.get(learner.state_dict.remote())
        except checkpoint.CheckpointError as error:
            raise RolloutError(f"the learner died ({cause}), and {error}") from None
        state = {**state, "version": max(int(state["version"]), service.version) + 1}
        load_into(learner, state)
        service.replace_learner(learner)
        self.learner = learner
        log.warning(
            "the learner died (%s); restored from %s at step %d (restart %d of at most %d)",
            cause,
            source,
            int(state["step"]),
            restart,
            self.max_restarts,
        )
        return learner
