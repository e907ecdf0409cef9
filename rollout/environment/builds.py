"""Which executable a ``--env`` names: a Unity build's path, ``unitysim:<Env>`` (the
stand-in, written as a launcher on first use), or the editor. Light to import (no
mlagents communicator, no gRPC), so the driver checks it before Ray starts."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from mlagents_envs import env_utils

UNITYSIM_PREFIX = "unitysim:"
BUILD_SUFFIXES = (".x86_64", ".x86")


class UnityError(RuntimeError):
    """A problem no restart can fix (bad build path, incompatible version, budget spent)."""


def unitysim_builds_dir() -> Path:
    return Path(tempfile.gettempdir()) / f"unity-rollout-{os.getuid()}" / "unitysim-builds"


def resolve_build(build: str | None) -> str | None:
    """The executable to launch for ``build`` (None: editor mode), or a one-line error."""
    if build is None:
        return None
    if build.startswith(UNITYSIM_PREFIX):
        from unitysim.launcher import build as build_launchers

        name = build[len(UNITYSIM_PREFIX) :]
        try:
            (launcher,) = build_launchers(unitysim_builds_dir(), [name])
        except ValueError as error:
            raise UnityError(str(error)) from None
        return str(launcher)
    executable = env_utils.validate_environment_path(build)
    if executable is None:
        stem = next((build[: -len(s)] for s in BUILD_SUFFIXES if build.endswith(s)), build)
        raise UnityError(
            f"no Unity build at {build!r}: expected an executable {stem}.x86_64 (or the path "
            f"of one), or use unitysim:<Env> for the headless stand-in"
        )
    if not os.access(executable, os.X_OK):
        raise UnityError(f"Unity build {executable!r} is not executable: run chmod +x on it")
    return executable
