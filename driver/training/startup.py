"""How long a user waits: seconds from the process's start to the first environment step
and to the first summary with a mean reward (``summary.json``'s ``startup``)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import psutil

if TYPE_CHECKING:
    from rollout.serving.service import RolloutService


def first_steps(service: RolloutService) -> list[float]:
    """When each worker's Unity first answered (wall clock), as far as reported."""
    return [w.first_step_at for w in service.metrics.workers if w.first_step_at is not None]


def startup_times(
    first_steps: list[float], first_reward_at: float | None
) -> dict[str, float | None]:
    """Seconds from this process's start to the first environment step and the first
    summary with a mean reward (what a user waits for before anything happens), and both
    moments as wall-clock times (for a benchmark that times the launch itself)."""
    launched = time.time() - process_age()
    first_step = min(first_steps, default=None)

    def since(at: float | None) -> float | None:
        return None if at is None else round(at - launched, 2)

    return {
        "first_step_s": since(first_step),
        "first_summary_s": since(first_reward_at),
        "first_step_at": first_step,
        "first_summary_at": first_reward_at,
    }


def process_age() -> float:
    """Seconds since this process started, to 10 ms. psutil's create_time is off by up to
    a second on Linux (it adds the boot time, which the kernel gives in whole seconds)."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        started = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # since boot
        return time.clock_gettime(time.CLOCK_BOOTTIME) - started
    except (OSError, ValueError, IndexError, AttributeError):
        return time.time() - psutil.Process().create_time()
