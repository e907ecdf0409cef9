"""Launchers that make unitysim look like a Linux Unity build to ``mlagents_envs``.

``env_utils.launch_executable`` strips ``.x86_64`` from ``file_name`` and looks for
``<file_name>.x86_64``; it kills only the PID it started, so the launcher must ``exec``.
"""

from __future__ import annotations

import os
import shlex
import sys
from collections.abc import Iterable
from pathlib import Path

from unitysim.envs import NAMES

SUFFIX = ".x86_64"
_PACKAGE_ROOT = Path(__file__).resolve().parent.parent

_TEMPLATE = """#!/bin/sh
# unitysim stand-in for the Unity build "{name}" (made by `python -m unitysim build`).
# Arguments are a Unity player's: --mlagents-port N, -logFile PATH, -nographics, ...
export PYTHONPATH={root}"${{PYTHONPATH:+:$PYTHONPATH}}"
export GRPC_VERBOSITY="${{GRPC_VERBOSITY:-ERROR}}"
exec {python} -m unitysim play --env {quoted_name} "$@"
"""


def launcher_path(directory: Path | str, name: str) -> Path:
    return Path(directory) / f"{name}{SUFFIX}"


def build(
    directory: Path | str, names: Iterable[str] = NAMES, python: str | None = None
) -> list[Path]:
    """Write ``<directory>/<Env>.x86_64`` for each environment; returns their paths.

    ``UnityEnvironment(file_name=str(directory / Env))`` then launches it like a build.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in names:
        if name not in NAMES:
            raise ValueError(
                f"unknown unitysim environment {name!r}; choose from {', '.join(NAMES)}"
            )
        path = launcher_path(directory, name)
        text = _TEMPLATE.format(
            name=name,
            quoted_name=shlex.quote(name),
            root=shlex.quote(str(_PACKAGE_ROOT)),
            python=shlex.quote(python or sys.executable),
        )
        write_executable(path, text)
        paths.append(path)
    return paths


def write_executable(path: Path, text: str) -> None:
    """Write an executable script unless it already holds ``text``. Atomic, and safe for
    concurrent writers (each has its own temporary file): none sees a half-written file."""
    if path.exists() and path.read_text() == text:
        return
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    tmp.chmod(0o755)
    tmp.replace(path)
