"""Hyper-parameter schedules, as ML-Agents names them in trainer configs."""

from __future__ import annotations

LR_END, EPSILON_END, BETA_END = 1e-10, 0.1, 1e-5  # where ML-Agents' linear schedules end


def decay(value: float, progress: float, schedule: str, end: float = LR_END) -> float:
    """``linear``: from ``value`` at the start to ``end`` at ``max_steps`` (progress 1),
    as ML-Agents' ``DecayedValue``; ``constant``: ``value`` throughout."""
    if schedule == "constant":
        return value
    progress = min(max(progress, 0.0), 1.0)
    return (value - end) * (1.0 - progress) + end
