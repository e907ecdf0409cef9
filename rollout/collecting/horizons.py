"""Where each behavior's trajectories are cut: its own ``time_horizon``."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from batches.contracts import base_name


@dataclass(frozen=True)
class Horizons:
    """Where each behavior's rows are cut: its own ``time_horizon``, as ML-Agents cuts each
    behavior's trajectories; ``behaviors`` is keyed as trainer configs name them (without
    ``?team=``), ``default`` serves the others."""

    default: int = 64
    behaviors: Mapping[str, int] = field(default_factory=dict)

    @classmethod
    def of(cls, horizon: int | Horizons) -> Horizons:
        return horizon if isinstance(horizon, Horizons) else cls(horizon)

    def __call__(self, behavior: str) -> int:
        return self.behaviors.get(base_name(behavior), self.default)

    @property
    def shortest(self) -> int:
        """The shortest configured row: the least a collect should ask for."""
        return min(self.behaviors.values()) if self.behaviors else self.default
