"""Small helpers shared by the tests that start processes."""

from __future__ import annotations

import contextlib
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import psutil

from rollout.ports import PortAllocator, PortRange


def free_port() -> int:
    """A port nothing listens on right now (for tests that bypass the port allocator)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def wait_gone(pid: int, seconds: float) -> bool:
    """Whether process ``pid`` is gone (or a zombie) within ``seconds``."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            if psutil.Process(pid).status() == psutil.STATUS_ZOMBIE:
                return True
        except psutil.NoSuchProcess:
            return True
        time.sleep(0.05)
    return False


@contextlib.contextmanager
def leak_checked_allocator(
    tmp_path: Path, first: int, last: int, **kwargs: float
) -> Iterator[PortAllocator]:
    """A port allocator with its own range and registry that fails the test if a port is
    still leased at the end (every test's ports must go back)."""
    allocator = PortAllocator(PortRange(first, last), tmp_path / "ports", **kwargs)
    yield allocator
    assert allocator.leases() == {}, "a test left a port leased"
