"""Session-wide guards: every process a test starts must be gone when it ends.

Players and other helpers inherit ``UNITY_ROLLOUT_TEST_SESSION``; after each test we look
for live processes carrying it (children, and orphans re-parented elsewhere). Kept free of
heavy imports: ``tests/compat`` also runs under other interpreters.
"""

from __future__ import annotations

import os
import time
import uuid

import pytest

SESSION_TAG = "UNITY_ROLLOUT_TEST_SESSION"
os.environ.setdefault(SESSION_TAG, uuid.uuid4().hex)


def tagged_processes() -> list:
    """Live processes (not us) that inherited this test session's tag."""
    import psutil

    tag, me, found = os.environ[SESSION_TAG], os.getpid(), []
    for process in psutil.process_iter(["pid", "status"]):
        if process.pid == me or process.info["status"] == psutil.STATUS_ZOMBIE:
            continue
        try:
            if process.environ().get(SESSION_TAG) == tag:
                found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, ProcessLookupError):
            continue
    return found


@pytest.fixture(autouse=True)
def no_leftover_processes(request):
    yield
    try:
        import psutil  # noqa: F401
    except ImportError:  # the compat suite under other interpreters starts no processes
        return
    deadline = time.monotonic() + 10.0
    left = tagged_processes()
    while left and time.monotonic() < deadline:
        time.sleep(0.2)
        left = tagged_processes()
    if left:
        details = [f"{p.pid}: {' '.join(p.cmdline())[:200]}" for p in left]
        for process in left:
            process.kill()
        pytest.fail(f"test left processes behind: {details}")
