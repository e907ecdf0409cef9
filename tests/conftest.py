"""Session-wide guards: every process a test starts must be gone when it ends.

Players and other helpers inherit ``UNITY_ROLLOUT_TEST_SESSION``; after each test we look
for live processes carrying it (children, and orphans re-parented elsewhere). Kept free of
heavy imports: ``tests/compat`` also runs under other interpreters.
"""

from __future__ import annotations

import os
import uuid

import pytest

from tests.waiting import poll_until

SESSION_TAG = "UNITY_ROLLOUT_TEST_SESSION"
os.environ.setdefault(SESSION_TAG, uuid.uuid4().hex)
# pytest-xdist's workers inherit the controller's tag: each gets its own, so that one
# worker's checks never count the processes of a test running on another
if (worker := os.environ.get("PYTEST_XDIST_WORKER")) and not os.environ[SESSION_TAG].endswith(
    f"-{worker}"
):
    os.environ[SESSION_TAG] += f"-{worker}"


# One math thread per process: the suite runs three pytest workers on two cores, and
# torch's OpenMP threads then spin against each other (an in-process cloning test took
# 83 s with two threads beside other work, 1.2 s with one). What the product sets itself
# (the learner's --learner-threads) is unchanged.
os.environ.setdefault("OMP_NUM_THREADS", "1")


RAY_MARKERS = ("raylet", "gcs_server", "ray/", "ray::", "default_worker", "dashboard")


def is_ray_process(process) -> bool:
    """Ray's own processes live for the whole session (one shared ``ray.init``)."""
    try:
        command = " ".join(process.cmdline())
    except Exception:
        return False
    return any(marker in command for marker in RAY_MARKERS)


def tagged_processes(include_ray: bool = False) -> list:
    """Live processes (not us) that inherited this test session's tag."""
    import psutil

    tag, me, found = os.environ[SESSION_TAG], os.getpid(), []
    for process in psutil.process_iter(["pid", "status"]):
        if process.pid == me or process.info["status"] == psutil.STATUS_ZOMBIE:
            continue
        try:
            if process.environ().get(SESSION_TAG) == tag and (
                include_ray or not is_ray_process(process)
            ):
                found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, ProcessLookupError):
            continue
    return found


def wait_for_no_processes(include_ray: bool, seconds: float = 10.0) -> list[str]:
    """Wait for tagged processes to end; kill and describe those that do not."""
    poll_until(lambda: not tagged_processes(include_ray), seconds, every=0.2)
    left = tagged_processes(include_ray)
    details = []
    for process in left:
        try:
            command = " ".join(process.cmdline())
            details.append(f"{process.pid} (parent {process.ppid()}): {command[:300]}")
            process.kill()
        except Exception:
            continue
    return details


@pytest.fixture(autouse=True)
def no_leftover_processes(request):
    yield
    try:
        import psutil  # noqa: F401
    except ImportError:  # the compat suite under other interpreters starts no processes
        return
    if left := wait_for_no_processes(include_ray=False):
        pytest.fail(f"test left processes behind: {left}")


@pytest.fixture(scope="session")
def ray_session():
    """One local Ray for the whole session (it takes ~6 s to start), 2 CPUs as in CI."""
    import ray

    from driver.local_ray import init_local_ray

    init_local_ray(2)
    session = ray._private.worker._global_node.session_name  # to tell its processes apart
    yield ray
    ray.shutdown()
    if left := wait_for_no_processes(include_ray=True, seconds=20.0):
        pytest.fail(f"Ray left processes behind after shutdown (this fixture's {session}): {left}")
