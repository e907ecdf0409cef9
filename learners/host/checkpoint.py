"""Checkpoint files: everything a run needs to resume, or to export its policies.

One ``torch.save`` file per checkpoint, plain data only (tensors, numbers, strings, lists
and dicts), so ``torch.load(weights_only=True)`` reads it and a checkpoint never executes
code. Behavior specs are stored as dicts (``spec_to_dict``), because ``BehaviorSpec`` is a
class. Layout::

    {"format": 2, "step": int, "version": int, "meta": {...},
     "behaviors": {behavior: {"spec": dict, "trainer_type": str, "network_settings": dict,
                              "network": state_dict, "algorithm": dict,
                              "steps": int, "updates": [int]}}}

A run keeps one folder per behavior, ``checkpoints/<behavior>/step-<N>.pt``, each file
holding that behavior (the driver's ``driver/training/checkpoints.py``); loading a run directory
takes each behavior's newest readable file and joins them into the layout above.

Writes go to a temporary file, synced, then renamed into place, so a kill or a crash
mid-write never leaves a truncated checkpoint behind the name of a good one.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch

from batches.specs import spec_from_dict, spec_to_dict
from learners.networks.policies import ActorCritic
from learners.trainer_config.settings import MemorySettings, NetworkSettings

__all__ = ["load", "networks", "newest_first", "save", "spec_from_dict", "spec_to_dict"]

# The layout's version: a file of another format is refused in one line instead of read
# into state it does not hold. 2: SAC's own Q layout and gradient counts, self-play's
# snapshot keys, every behavior's trainer type and memory settings.
FORMAT = 2
log = logging.getLogger(__name__)


class CheckpointError(ValueError):
    """A checkpoint that cannot be read; the message names the file."""


def save(path: str | Path, state: dict[str, Any]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as file:
        torch.save({"format": FORMAT, **state}, file)
        file.flush()
        os.fsync(file.fileno())
    os.replace(tmp, path)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)  # the rename itself survives a power cut
    finally:
        os.close(folder)
    return path


def read(path: str | Path) -> dict[str, Any]:
    """One checkpoint file; CheckpointError names it when it cannot be read."""
    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile) as e:
        reason = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise CheckpointError(f"{path}: unreadable checkpoint ({reason})") from None
    if not isinstance(state, dict) or not isinstance(state.get("format"), int):
        raise CheckpointError(f"{path}: not a unity-rollout checkpoint (format {FORMAT})")
    if state["format"] != FORMAT:
        raise CheckpointError(
            f"{path}: a checkpoint of format {state['format']}, this unity-rollout reads format "
            f"{FORMAT}; start a new run (another --run-id) or resume with the version that wrote it"
        )
    return state


def newest_first(folder: Path) -> list[Path]:
    """A folder's checkpoints, the newest written first."""
    return sorted(folder.glob("*.pt"), key=lambda p: p.stat().st_mtime_ns, reverse=True)


def _newest_readable(folder: Path) -> dict[str, Any] | None:
    """The newest checkpoint of ``folder`` that reads; each one skipped is said."""
    first_problem = None
    for path in newest_first(folder):
        try:
            state = read(path)
        except CheckpointError as error:
            log.warning("%s; trying the one before it", error)
            first_problem = first_problem or error
            continue
        if first_problem is not None:
            log.warning("using %s instead", path)
        return {**state, "files": [str(path)]}
    if first_problem is not None:
        raise CheckpointError(f"{folder}: no readable checkpoint (newest: {first_problem})")
    return None


def load(path: str | Path) -> dict[str, Any]:
    """A checkpoint file, or a run (or its ``checkpoints/`` folder): every behavior from
    its newest readable file, the version the newest of theirs; ``files`` names them."""
    path = Path(path)
    if not path.is_dir():
        return {**read(path), "files": [str(path)]}
    folder = path / "checkpoints" if (path / "checkpoints").is_dir() else path
    parts = [
        state
        for sub in sorted(p for p in folder.iterdir() if p.is_dir())
        if (state := _newest_readable(sub)) is not None
    ]
    if not parts:  # a run written before per-behavior folders: one file, all behaviors
        parts = [state] if (state := _newest_readable(folder)) is not None else []
    if not parts:
        raise FileNotFoundError(f"{folder}: no checkpoint (*.pt) found")
    behaviors = {name: entry for part in parts for name, entry in part["behaviors"].items()}
    newest = max(parts, key=lambda part: int(part["version"]))
    return {
        **newest,
        "step": sum(int(part["step"]) for part in parts),
        "version": int(newest["version"]),
        "behaviors": behaviors,
        "files": [file for part in parts for file in part["files"]],
    }


def networks(state: dict[str, Any]) -> dict[str, ActorCritic]:
    """Rebuild each behavior's network with its trained weights (for export and replay)."""
    built = {}
    for behavior, entry in state["behaviors"].items():
        settings = network_settings(entry["network_settings"])
        network = ActorCritic(spec_from_dict(entry["spec"]), settings)
        network.load_state_dict(entry["network"])
        built[behavior] = network.eval()
    return built


def network_settings_dict(settings: NetworkSettings) -> dict[str, Any]:
    return dataclasses.asdict(settings)


def network_settings(saved: dict[str, Any]) -> NetworkSettings:
    """``network_settings_dict``'s inverse (the memory section a dataclass again)."""
    memory = saved.get("memory")
    return NetworkSettings(**{**saved, "memory": MemorySettings(**memory) if memory else None})
