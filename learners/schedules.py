"""Hyper-parameter schedules, as ML-Agents names them in trainer configs."""

from __future__ import annotations


def linear_decay(value: float, progress: float, schedule: str, floor: float = 1e-10) -> float:
    """``linear``: from ``value`` at the start to ``floor`` at ``max_steps``; ``constant``."""
    if schedule == "constant":
        return value
    return max(value * (1.0 - min(max(progress, 0.0), 1.0)), floor)
