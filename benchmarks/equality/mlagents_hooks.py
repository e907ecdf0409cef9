"""Run the anchor's mlagents-learn launcher with a patch put in at run time: the patch runs
once ``mlagents.trainers.trainer_controller`` is imported (the launcher's own workarounds
have run by then), so nothing in site-packages is edited. Standard library only: this runs
under the anchor's own Python, imported by ``mlagents_update_log.py`` and
``bench_mlagents_normalizer.py`` run there as plain files (by their paths)."""

from __future__ import annotations

import builtins
import runpy
import sys
from collections.abc import Callable
from typing import Any


def run_patched(patch: Callable[[], None], launcher: str, argv: list[str]) -> None:
    """``launcher`` run as ``__main__`` with ``argv`` (its own path first), ``patch`` in."""
    sys.argv = argv
    plain = builtins.__import__

    def hooked(name: str, *args: Any, **kwargs: Any) -> Any:
        module = plain(name, *args, **kwargs)
        if name == "mlagents.trainers.trainer_controller":
            builtins.__import__ = plain
            patch()
        return module

    builtins.__import__ = hooked
    runpy.run_path(launcher, run_name="__main__")
