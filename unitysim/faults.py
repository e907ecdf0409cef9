"""Faults on demand, so that the rollout side's failure handling can be tested for real.

Each fault is a command-line flag of the player (extra arguments of ``UnityEnvironment``
reach it verbatim) or an environment variable (``UNITYSIM_CRASH_AFTER=3``); a flag wins.
"After N" counts environment steps (STEP exchanges) after the first reset.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, fields


@dataclass(frozen=True)
class Faults:
    crash_after: int | None = None  # exit with code 3, like a crashing player
    hang_after: int | None = None  # stop answering (Python times out), exit when orphaned
    delay_ms: float = 0.0  # answer every exchange this much later
    status_after: int | None = None  # send header status ``status_code`` instead of 200
    status_code: int = 500
    oversize_after: int | None = None  # send a message over gRPC's 4 MiB limit
    nan_after: int | None = None  # send NaN observations
    silent_after: int | None = None  # no agent asks for a decision (Behavior Type: Heuristic)
    communication_version: str | None = None  # announce this API version in the handshake

    @classmethod
    def add_arguments(cls, parser: argparse.ArgumentParser) -> None:
        group = parser.add_argument_group("faults (also UNITYSIM_<NAME> environment variables)")
        for item in fields(cls):
            flag = "--sim-" + item.name.replace("_", "-")
            kind = str if item.name == "communication_version" else float
            kind = int if item.name.endswith(("_after", "_code")) else kind
            group.add_argument(flag, dest=f"fault_{item.name}", type=kind, default=None)

    @classmethod
    def from_arguments(cls, args: argparse.Namespace) -> Faults:
        values = {}
        for item in fields(cls):
            value = getattr(args, f"fault_{item.name}", None)
            if value is None:
                raw = os.environ.get(f"UNITYSIM_{item.name.upper()}")
                if raw:
                    value = raw if item.name == "communication_version" else float(raw)
                    if item.name.endswith(("_after", "_code")):
                        value = int(float(raw))
            if value is not None:
                values[item.name] = value
        return cls(**values)

    def due(self, after: int | None, step: int) -> bool:
        return after is not None and step >= after
