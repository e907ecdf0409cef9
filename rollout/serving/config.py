"""What configures the rollout service (``rollout/serving/service.py``) and what it raises."""

from __future__ import annotations

import re
from dataclasses import dataclass

from rollout.collecting.horizons import Horizons
from rollout.environment.ports import PortRange
from rollout.environment.unity import UnityConfig


class RolloutError(RuntimeError):
    """Collection cannot go on (a worker keeps failing); the message names the cause."""


class LearnerDied(RuntimeError):
    """The learner actor is gone (OOM, a GPU error, SIGKILL). The driver brings a new one
    back from the last checkpoint and hands it to ``replace_learner``; the workers keep
    their Unity instances and weights meanwhile."""


def last_line(error: Exception) -> str:
    """What a Ray error says in one line: its last, or for an out-of-memory kill which
    node ran out (Ray's message ends in a table of processes)."""
    text = str(error).strip()
    if (memory := out_of_memory(text)) is not None:
        return memory
    return text.splitlines()[-1] if text else type(error).__name__


# Ray's memory monitor, 2.x: "Memory on the node (IP: 10.0.0.5, ID: ...) was 30.1GB used /
# 31.2GB limit (...)"; before 2.40: "... where the task (...) was running was 30.1GB / 31.2GB"
_RAY_MEMORY = re.compile(
    r"Memory on the node \(IP: (?P<ip>[^,]+),.*?was (?P<used>[\d.]+) ?GB(?: used)? / "
    r"(?P<total>[\d.]+) ?GB",
    re.S,
)


OUT_OF_MEMORY = "ran out of memory"


def out_of_memory(text: str) -> str | None:
    """One line for a process that Ray's memory monitor killed, else None."""
    if "low on memory" not in text and "OutOfMemoryError" not in text:
        return None
    found = _RAY_MEMORY.search(text)
    where = (
        f" on node {found['ip']} ({found['used']} GB of {found['total']} GB in use)"
        if found
        else ""
    )
    return f"{OUT_OF_MEMORY}{where}: Ray's memory monitor killed it"


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
    # follow the cluster's size (--workers auto, rollout/serving/membership.py): workers join with
    # new nodes, and leave with theirs without failing the run
    elastic: bool = False
    learner_cpus: float = 1.0  # elastic: the CPUs no worker counts on
    max_workers: int | None = None  # elastic: at most this many
    restart_wait_s: float = 120.0  # how long a worker may take to come back after a death
    port_range: PortRange | None = None
    registry_dir: str | None = None
