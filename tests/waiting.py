"""Waits on a state itself (a file, a process, a port, a Ray actor's answer), never on a
clock: the one place the tests look again and again at what no event announces. Light
(no torch): ``tests/conftest.py`` imports it, and ``tests/compat`` runs under other
interpreters."""

from __future__ import annotations

import time
from collections.abc import Callable

POLL_S = 0.05  # how often a wait below looks again at what it waits for


def poll_until(condition: Callable[[], object], seconds: float, every: float = POLL_S) -> bool:
    """Whether ``condition()`` held within ``seconds`` (a safety stop, not a pace): the one
    place the tests look again and again at a state no event announces (a file, a process,
    a port, a Ray actor's answer). ``every``: longer where a look costs (a scan of processes)."""
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(every)
    return True


def wait_for(condition: Callable[[], object], what: str, seconds: float = 120) -> None:
    """``poll_until``, failing the test with ``what`` it waited for at the safety stop."""
    assert poll_until(condition, seconds), f"{what}: not within {seconds:g} s (a safety stop)"
