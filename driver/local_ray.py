"""Local mode's Ray: one node on this machine, and a way to start it in the background.

``init_local_ray`` is the blocking start (tests, ``collect``). ``BackgroundRay`` starts
the same Ray on a thread, so that the few seconds Ray takes to come up overlap the
driver's own imports (torch, tensordict, torchrl take as long again); ``train`` waits for
it just before it needs it. The thread stays alive until ``shutdown``: Ray's node
processes die with the thread that started them (their parent-death signal is bound to
it), so a thread that returned would take the node down with it.

Under load a start can fail on a timing of Ray's own: the raylet gives its dashboard agent
15 s to write its ports, and dies when the agent (a Python process) has not by then. The
wait for the raylet to register notices that at once, and the lean head starts again, up to
``LEAN_TRIES`` times and on until ``START_WAIT_S`` has passed, instead of polling a dead
raylet for minutes; if Ray still does not start, ``RayStartError`` says so in one line.

Local mode also leaves out three of the helper processes Ray's head starts, none of which
a local run uses: the autoscaler monitor (nothing to scale), the log monitor (worker
output goes to Ray's log files, not to the driver: ``log_to_driver=False``) and the
dashboard head (``--dashboard`` starts Ray with it). ``ray.init`` has no switch for them,
so ``_lean_head`` adjusts Ray's own node class for the length of the call; if that fails
for any reason, plain ``ray.init`` runs instead.

Ray's thread starts each process with a ``preexec_fn``, so each start runs Python's fork
hooks: the before-fork ones, the fork, the after-fork ones. A module that registers a
pair (``before=lock.acquire, after_in_parent=lock.release``) between the two, imported by
the main thread meanwhile, gets only its release run: "RuntimeError: release unlocked
lock", printed as ignored in ``_fork_exec``. ``concurrent.futures.thread`` is the one
such module the driver's imports (torch's) bring in, so it is imported here, first.
"""

from __future__ import annotations

import concurrent.futures.thread  # noqa: F401  (its fork hooks, before Ray's thread forks)
import contextlib
import logging
import os
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil
import ray
import ray._private.node
import ray._private.ray_constants
import ray._private.services
import ray._private.worker

# Ray's own figures: the smallest object store it accepts, and its default share of memory.
RAY_MIN_OBJECT_STORE = 75 * 1024**2
RAY_OBJECT_STORE_SHARE = 0.3
GCS_WAIT = "RAY_gcs_server_port_wait_time_s"  # Ray's variable: seconds for its GCS to start
DASHBOARD_WAIT = "RAY_DASHBOARD_STARTUP_TIMEOUT_S"  # Ray's wait for its dashboard (60 s)
START_WAIT_S = 180  # our wait for each (Ray's own runs out on a loaded node); deploy/ sets it too
NODE_POLL_S = 0.02  # how often ray.init asks the GCS whether its raylet has registered
NODE_WAIT_S = 180.0  # give up polling, and leave the wait to Ray, after this long
LEAN_PROCESSES = ("monitor", "log_monitor", "dashboard")  # Ray's names for what we leave out
# lean heads whose raylet died before registering, before Ray's full head: at least this
# many, and more until START_WAIT_S has passed
LEAN_TRIES = 3

log = logging.getLogger(__name__)


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


class RayletExited(Exception):
    """The raylet died before it registered (not a RuntimeError: Ray's own wait for the
    node retries those for 30 s)."""


def _raylet_failure(logs: Path) -> str:
    """What the raylet said as it died: its last fatal record (``C``), shortened."""
    try:
        records = (logs / "raylet.out").read_text(errors="replace").splitlines()
    except OSError:
        return f"no raylet.out in {logs}"
    fatal = [r for r in records if " C " in r[:40]]  # [date time C pid tid] (raylet) ...
    if not fatal:
        return f"see {logs / 'raylet.out'}"
    said = fatal[-1].split("Check failed: ", 1)[-1]
    return said.split(".has_value() ", 1)[-1][:300]


@dataclass
class _Raylets:
    """The raylets a lean head started, for the wait on their registration to watch."""

    started: list[tuple[subprocess.Popen, Path]] = field(default_factory=list)

    def check(self) -> None:
        for process, logs in self.started:
            if (code := process.poll()) is not None:
                raise RayletExited(f"exit {code}: {_raylet_failure(logs)}")


def _lean_node_class(node: type, raylets: _Raylets) -> type:
    class LeanNode(node):  # type: ignore[misc,valid-type]
        """Ray's head node without the autoscaler monitor, log monitor and dashboard head."""

        def start_ray_processes(self) -> None:
            super().start_ray_processes()
            logs = Path(self.get_logs_dir_path())
            kind = ray._private.ray_constants.PROCESS_TYPE_RAYLET
            raylets.started += [(i.process, logs) for i in self.all_processes.get(kind, [])]

        def __init__(self, ray_params: Any, *args: Any, **kwargs: Any) -> None:
            ray_params.no_monitor = True
            ray_params.include_log_monitor = False
            try:
                super().__init__(ray_params, *args, **kwargs)
            except BaseException:
                # A head that failed half-way (its raylet never registered): what it had
                # started lives as long as this thread, beside the plain head that follows.
                with contextlib.suppress(Exception):
                    self.kill_all_processes(check_alive=False, wait=True)
                raise

        def start_api_server(self, *, include_dashboard: Any, raise_on_failure: Any) -> None:
            self._webui_url = None  # what the node reports where no dashboard runs

    return LeanNode


def _prompt_get_node(get_node: Any, raylets: _Raylets) -> Any:
    """Ray's ``get_node`` asks the GCS for the new raylet once a second; ours asks every
    20 ms first, so ``ray.init`` goes on as soon as the raylet registers (about 1.5 s
    after it starts here, which Ray's own poll rounds up to 2 s). It stops at once with
    ``RayletExited`` if the raylet died; a GCS slow to answer is asked again."""

    def prompt(gcs_address: str, node_id: str) -> Any:
        give_up = time.monotonic() + NODE_WAIT_S
        client = None
        while time.monotonic() < give_up:
            raylets.check()
            try:
                client = client or ray._raylet.GcsClient(address=gcs_address)
                if any(n.hex() == node_id for n in client.get_all_node_info(timeout=5)):
                    break
            except (AttributeError, TypeError):  # Ray's internals moved: its own wait decides
                break
            except Exception:  # a GCS busy past the call's 5 s: ask again
                log.debug("the GCS did not answer yet", exc_info=True)
            time.sleep(NODE_POLL_S)
        return get_node(gcs_address, node_id)

    return prompt


@contextlib.contextmanager
def _lean_head() -> Iterator[None]:
    """For the length of a local ``ray.init``: the lean node class and the prompt poll.
    Both are Ray's private hooks (checked against the pinned Ray 2.60.0); they are put
    back afterwards, so worker processes and later calls see Ray unchanged."""
    node_module, services = ray._private.node, ray._private.services
    node, get_node = node_module.Node, services.get_node
    raylets = _Raylets()
    node_module.Node = _lean_node_class(node, raylets)
    services.get_node = _prompt_get_node(get_node, raylets)
    try:
        yield
    finally:
        node_module.Node, services.get_node = node, get_node


def init_local_ray(cpus: int, dashboard: bool = False) -> None:
    """No dashboard unless asked, no other helper this run does not use (``_lean_head``),
    and workers (with the Unity players they start) at the priority of the command that
    launched them; Ray's default, niceness 15, would hand their CPU to
    every other process on a shared machine. On a cluster the operator sets it at
    ``ray start`` (``RAY_worker_niceness``; deploy/README.md). The object store fits
    /dev/shm (``object_store_bytes``). Ray gives its GCS server 30 s to come up; with every
    core taken by other work that start took longer, and the run died in ``ray.init``:
    local mode waits up to 3 minutes unless the user set Ray's own variable, and as long for
    the dashboard (``--dashboard``; Ray's 60 s ran out beside two busy processes). Without
    the dashboard, workers report no task events: nothing would read them, and the GCS kept
    them all run long."""
    os.environ.setdefault(GCS_WAIT, str(START_WAIT_S))
    if dashboard:
        os.environ.setdefault(DASHBOARD_WAIT, str(START_WAIT_S))
    options: dict[str, Any] = {
        "num_cpus": cpus,
        "include_dashboard": dashboard,
        "log_to_driver": False,
        "object_store_memory": object_store_bytes(_shm_free(), psutil.virtual_memory().total),
        # task events feed the dashboard's task list; kept in the GCS, they grew it by
        # 190 MB in an hour of training (benchmarks/costs/bench_memory_flat.py)
        "_system_config": {"worker_niceness": 0}
        | ({} if dashboard else {"task_events_report_interval_ms": 0}),
        # Ray's own lines (a local instance started, token auth on, no SIGTERM handler off
        # the main thread) say nothing a local run's user acts on, and would follow an
        # error found meanwhile; with the dashboard, its address is worth the line
        "logging_level": logging.INFO if dashboard else logging.ERROR,
    }
    if dashboard:
        _plain_init(options, [])
        return
    deaths: list[str] = []
    give_up = time.monotonic() + START_WAIT_S
    while True:
        try:
            with _lean_head():
                ray.init(**options)
            return
        except RayletExited as error:  # a raylet that died starting on a busy machine
            deaths.append(str(error))
            again = len(deaths) < LEAN_TRIES or time.monotonic() < give_up
            log.warning(
                "Ray's raylet died before it registered (%s); %s",
                error,
                "starting it again" if again else "starting Ray's full head",
            )
            if not again:
                break
        except Exception as error:  # a Ray whose internals moved: start it the plain way
            log.warning("lean local Ray did not start (%s); starting Ray's full head", error)
            break
        finally:
            if not ray.is_initialized() and ray._private.worker._global_node is not None:
                ray.shutdown()  # a head that started, even if not connected
    _plain_init(options, deaths)


class RayStartError(Exception):
    """Local Ray did not come up within its waits: one line saying what was waited for."""


def _plain_init(options: dict[str, Any], deaths: list[str]) -> None:
    try:
        ray.init(**options)
    except Exception as error:
        said = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        before = (
            f"its raylet died {len(deaths)} times before registering (last: {deaths[-1]}), then "
            if deaths
            else ""
        )
        raise RayStartError(
            f"local Ray did not start on this machine: {before}Ray's own start said: {said} "
            f"(a machine this busy may need fewer other processes)"
        ) from error


class BackgroundRay:
    """``init_local_ray`` on a thread that lives until ``shutdown``."""

    def __init__(self, cpus: int, dashboard: bool = False) -> None:
        self._ready, self._stop = threading.Event(), threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(cpus, dashboard), daemon=True)
        self._thread.start()

    def _run(self, cpus: int, dashboard: bool) -> None:
        try:
            init_local_ray(cpus, dashboard)
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
