"""What configures the rollout service (``rollout/service.py``) and what it raises."""

from __future__ import annotations

from dataclasses import dataclass

from rollout.ports import PortRange
from rollout.segments import Horizons
from rollout.unity import UnityConfig


class RolloutError(RuntimeError):
    """Collection cannot go on (a worker keeps failing); the message names the cause."""


class LearnerDied(RuntimeError):
    """The learner actor is gone (OOM, a GPU error, SIGKILL). The driver brings a new one
    back from the last checkpoint and hands it to ``replace_learner``; the workers keep
    their Unity instances and weights meanwhile."""


def last_line(error: Exception) -> str:
    text = str(error).strip()
    return text.splitlines()[-1] if text else type(error).__name__


@dataclass(frozen=True)
class ServiceConfig:
    unity: UnityConfig
    num_workers: int = 2
    horizon: int | Horizons = 64  # steps after which a row is cut (ML-Agents' time_horizon)
    min_steps: int = 512  # steps of finished rows a collect call waits for (no demand)
    max_collect_s: float = 0.5  # ... or this long, so data and metrics keep flowing
    collects_per_worker: int = 1
    # steps collected beyond the learner's demand, acted by the weights its update replaces
    # (one version old when trained on): workers keep stepping through the update instead
    # of waiting for the slowest worker's last rows and the new weights
    collect_ahead: int = 0
    learner_in_flight: int = 2
    worker_cpus: float = 1.0
    # Wait for the learner's weights before the first collect (a resumed learner). A fresh
    # learner holds the factory's initial weights, which each worker builds for itself:
    # collection then starts while the learner's process is still starting.
    await_learner_weights: bool = True
    max_worker_restarts: int = 3
    # follow the cluster's size (--workers auto, rollout/membership.py): workers join with
    # new nodes, and leave with theirs without failing the run
    elastic: bool = False
    learner_cpus: float = 1.0  # elastic: the CPUs no worker counts on
    max_workers: int | None = None  # elastic: at most this many
    restart_wait_s: float = 120.0  # how long a worker may take to come back after a death
    port_range: PortRange | None = None
    registry_dir: str | None = None
