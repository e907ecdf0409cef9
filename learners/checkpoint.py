"""Checkpoint files: everything a run needs to resume, or to export its policies.

One ``torch.save`` file per checkpoint, plain data only (tensors, numbers, strings, lists
and dicts), so ``torch.load(weights_only=True)`` reads it and a checkpoint never executes
code. Behavior specs are stored as dicts (``spec_to_dict``), because ``BehaviorSpec`` is a
class. Layout::

    {"format": 1, "step": int, "version": int, "meta": {...},
     "behaviors": {behavior: {"spec": dict, "network_settings": dict,
                              "network": state_dict, "algorithm": dict}}}

Writes go to a temporary file renamed into place, so a crash mid-write never leaves a
truncated checkpoint behind the name of a good one.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import torch

from batches.specs import spec_from_dict, spec_to_dict
from learners.policies import ActorCritic
from learners.settings import NetworkSettings

__all__ = ["latest", "load", "networks", "save", "spec_from_dict", "spec_to_dict"]

FORMAT = 1


def save(path: str | Path, state: dict[str, Any]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save({"format": FORMAT, **state}, tmp)
    os.replace(tmp, path)
    return path


def load(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if path.is_dir():
        path = latest(path)
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise ValueError(f"{path}: not a unity-rollout checkpoint (format {FORMAT})")
    return state


def latest(directory: str | Path) -> Path:
    """The newest checkpoint in a run's ``checkpoints/`` directory (or the run directory)."""
    directory = Path(directory)
    if (directory / "checkpoints").is_dir():
        directory = directory / "checkpoints"
    found = sorted(directory.glob("*.pt"), key=lambda p: p.stat().st_mtime)
    if not found:
        raise FileNotFoundError(f"{directory}: no checkpoint (*.pt) found")
    return found[-1]


def networks(state: dict[str, Any]) -> dict[str, ActorCritic]:
    """Rebuild each behavior's network with its trained weights (for export and replay)."""
    built = {}
    for behavior, entry in state["behaviors"].items():
        settings = NetworkSettings(**entry["network_settings"])
        network = ActorCritic(spec_from_dict(entry["spec"]), settings)
        network.load_state_dict(entry["network"])
        built[behavior] = network.eval()
    return built


def network_settings_dict(settings: NetworkSettings) -> dict[str, Any]:
    return dataclasses.asdict(settings)
