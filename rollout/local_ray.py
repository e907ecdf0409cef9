"""Local mode's Ray: one node on this machine, and a way to start it in the background.

``init_local_ray`` is the blocking start (tests, ``collect``). ``BackgroundRay`` starts
the same Ray on a thread, so that the few seconds Ray takes to come up overlap the
driver's own imports (torch, tensordict, torchrl take as long again); ``train`` waits for
it just before it needs it. The thread stays alive until ``shutdown``: Ray's node
processes die with the thread that started them (their parent-death signal is bound to
it), so a thread that returned would take the node down with it.
"""

from __future__ import annotations

import os
import threading

import psutil
import ray

# Ray's own figures: the smallest object store it accepts, and its default share of memory.
RAY_MIN_OBJECT_STORE = 75 * 1024**2
RAY_OBJECT_STORE_SHARE = 0.3
GCS_WAIT = "RAY_gcs_server_port_wait_time_s"  # Ray's variable: seconds for its GCS to start


def object_store_bytes(shm_free: int, memory: int) -> int | None:
    """An object store that fits /dev/shm, or None for Ray's default.

    Ray's default (30 % of memory) does not fit a container's /dev/shm (``docker run
    --shm-size=2g`` on a 24 GiB host); Ray then moves the store to /tmp, slower, with a
    warning. Our segments are a few MB, so a store of what /dev/shm holds is plenty. Below
    Ray's minimum (Docker's default 64 MB) nothing fits: Ray's fallback and its hint stand."""
    default = int(memory * RAY_OBJECT_STORE_SHARE)
    fits = int(shm_free * 0.9)
    if fits >= default or fits < RAY_MIN_OBJECT_STORE:
        return None
    return fits


def _shm_free() -> int:
    try:
        stats = os.statvfs("/dev/shm")
    except OSError:  # no /dev/shm (not Linux): Ray does not use it either
        return 0
    return stats.f_bsize * stats.f_bavail


def init_local_ray(cpus: int) -> None:
    """No dashboard, and workers (with the Unity players they start) at the priority of
    the command that launched them; Ray's default, niceness 15, would hand their CPU to
    every other process on a shared machine. On a cluster the operator sets it at
    ``ray start`` (``RAY_worker_niceness``; deploy/README.md). The object store fits
    /dev/shm (``object_store_bytes``). Ray gives its GCS server 30 s to come up; with every
    core taken by other work that start took longer, and the run died in ``ray.init``:
    local mode waits up to 3 minutes unless the user set Ray's own variable."""
    os.environ.setdefault(GCS_WAIT, "180")
    ray.init(
        num_cpus=cpus,
        include_dashboard=False,
        log_to_driver=False,
        object_store_memory=object_store_bytes(_shm_free(), psutil.virtual_memory().total),
        _system_config={"worker_niceness": 0},
    )


class BackgroundRay:
    """``init_local_ray`` on a thread that lives until ``shutdown``."""

    def __init__(self, cpus: int) -> None:
        self._ready, self._stop = threading.Event(), threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(cpus,), daemon=True)
        self._thread.start()

    def _run(self, cpus: int) -> None:
        try:
            init_local_ray(cpus)
        except BaseException as error:  # handed to the caller of wait()
            self._error = error
        self._ready.set()
        self._stop.wait()

    def wait(self) -> None:
        """Block until Ray is up; re-raise what stopped it from starting."""
        self._ready.wait()
        if self._error is not None:
            raise self._error

    def shutdown(self) -> None:
        self._ready.wait()
        if ray.is_initialized():
            ray.shutdown()
        self._stop.set()
        self._thread.join(timeout=10)
