"""Node-wide port leases for Unity instances.

Every process on a node that starts Unity instances (any Ray job, or none) shares one
lease registry: a JSON file under a runtime directory, guarded by a file lock. A lease
names its owner (pid and process start time), so leases of dead owners are reclaimed. A
released port sits in quarantine (Linux keeps closed connections in TIME_WAIT) before it
is handed out again, and a port found busy (a foreign process holds it) is skipped for a
while. A lease is *pending* until our gRPC server has really bound the port on 127.0.0.1
with ``grpc.so_reuseport`` off (``confirm``): gRPC sets SO_REUSEPORT by default, which
would let two servers silently share a port.

Candidates come from a range outside the kernel's ephemeral ports and outside Ray's
worker ports (10002-19999), configurable with ``UNITY_ROLLOUT_PORT_RANGE=start-end``.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import socket
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import psutil
from filelock import FileLock

RANGE_VARIABLE = "UNITY_ROLLOUT_PORT_RANGE"
REGISTRY_VARIABLE = "UNITY_ROLLOUT_RUNTIME_DIR"
RAY_WORKER_PORTS = (10002, 19999)
DEFAULT_QUARANTINE_S = 60.0
FOREIGN_SKIP_S = 30.0


class PortError(RuntimeError):
    """A port could not be leased; the message says what to change."""


@dataclass(frozen=True)
class PortRange:
    start: int
    end: int  # inclusive

    def __post_init__(self) -> None:
        if not 1024 <= self.start <= self.end <= 65535:
            raise PortError(
                f"invalid port range {self.start}-{self.end}: "
                f"use {RANGE_VARIABLE}=START-END with 1024 <= START <= END <= 65535"
            )

    @classmethod
    def parse(cls, text: str) -> PortRange:
        try:
            start, end = (int(part) for part in text.split("-"))
        except ValueError:
            raise PortError(
                f"invalid port range {text!r}: expected START-END, e.g. 20000-29999"
            ) from None
        return cls(start, end)

    def __len__(self) -> int:
        return self.end - self.start + 1

    def __str__(self) -> str:
        return f"{self.start}-{self.end}"


def ephemeral_range() -> tuple[int, int]:
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999  # the Linux default


def default_range() -> PortRange:
    """``UNITY_ROLLOUT_PORT_RANGE``, else the ports between Ray's worker ports and the
    kernel's ephemeral range (20000-32767 on a default Linux)."""
    if configured := os.environ.get(RANGE_VARIABLE):
        return PortRange.parse(configured)
    start = RAY_WORKER_PORTS[1] + 1
    low, high = ephemeral_range()
    if low - 1 - start >= 256:
        return PortRange(start, low - 1)
    if high < 65535 - 256:
        return PortRange(max(start, high + 1), 65535)
    raise PortError(
        f"no room for Unity ports outside the ephemeral range {low}-{high} and Ray's worker "
        f"ports: set {RANGE_VARIABLE}=START-END"
    )


def default_registry_dir() -> Path:
    if configured := os.environ.get(REGISTRY_VARIABLE):
        return Path(configured)
    base = Path("/dev/shm") if Path("/dev/shm").is_dir() else Path(tempfile.gettempdir())
    return base / f"unity-rollout-{os.getuid()}"


def process_start_time(pid: int) -> float | None:
    try:
        return psutil.Process(pid).create_time()
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return None


def port_is_free(port: int) -> bool:
    """Whether a server could bind 127.0.0.1:port as gRPC would (SO_REUSEADDR, no
    SO_REUSEPORT): fails if anyone listens on it, on 127.0.0.1 or a wildcard address."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


class PortAllocator:
    """Leases ports from one node-wide registry. Safe across threads and processes."""

    def __init__(
        self,
        port_range: PortRange | None = None,
        registry_dir: Path | str | None = None,
        quarantine_s: float = DEFAULT_QUARANTINE_S,
    ) -> None:
        self.port_range = port_range or default_range()
        self.registry_dir = Path(registry_dir) if registry_dir else default_registry_dir()
        self.registry_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        self.quarantine_s = quarantine_s
        self._path = self.registry_dir / "ports.json"
        self._lock = FileLock(str(self.registry_dir / "ports.lock"))

    # --- registry I/O ------------------------------------------------------------------

    @contextlib.contextmanager
    def _registry(self) -> Iterator[dict]:
        """The registry, locked; changes are written back atomically."""
        with self._lock:
            try:
                state = json.loads(self._path.read_text())
            except (FileNotFoundError, json.JSONDecodeError):
                state = {}
            state.setdefault("leases", {})
            state.setdefault("quarantine", {})
            state.setdefault("foreign", {})
            self._expire(state, time.time())
            yield state
            tmp = self._path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(json.dumps(state))
            tmp.replace(self._path)

    def _expire(self, state: dict, now: float) -> None:
        owners = {(lease["pid"], lease["start"]) for lease in state["leases"].values()}
        dead = {(pid, start) for pid, start in owners if process_start_time(pid) != start}
        for port, lease in list(state["leases"].items()):
            if (lease["pid"], lease["start"]) in dead:  # the owner is gone
                del state["leases"][port]
                state["quarantine"][port] = now + self.quarantine_s
        for table in ("quarantine", "foreign"):
            state[table] = {p: t for p, t in state[table].items() if t > now}

    # --- leasing -----------------------------------------------------------------------

    def lease(self, owner_pid: int | None = None) -> int:
        """A free port, leased (pending) to ``owner_pid`` (default: this process)."""
        pid = owner_pid or os.getpid()
        start = process_start_time(pid)
        if start is None:
            raise PortError(f"cannot lease a port for process {pid}: it does not exist")
        candidates = list(range(self.port_range.start, self.port_range.end + 1))
        offset = random.randrange(len(candidates))  # spread concurrent leasers apart
        with self._registry() as state:
            now = time.time()
            for port in candidates[offset:] + candidates[:offset]:
                key = str(port)
                if key in state["leases"] or key in state["quarantine"] or key in state["foreign"]:
                    continue
                if not port_is_free(port):
                    state["foreign"][key] = now + FOREIGN_SKIP_S
                    continue
                state["leases"][key] = {"pid": pid, "start": start, "bound": False, "at": now}
                return port
            taken = Counter(
                next(t for t in ("leases", "quarantine", "foreign") if str(port) in state[t])
                for port in candidates
            )
            raise PortError(
                f"no free port in {self.port_range} ({len(candidates)} ports): "
                f"{taken['leases']} leased, {taken['quarantine']} in quarantine, "
                f"{taken['foreign']} held by other programs; widen it with "
                f"{RANGE_VARIABLE}=START-END (for example 20000-29999)"
            )

    def lease_port(self, port: int, owner_pid: int | None = None) -> int:
        """Lease one given port (editor mode's 5004), or fail saying who holds it."""
        pid = owner_pid or os.getpid()
        with self._registry() as state:
            holder = state["leases"].get(str(port))
            if holder is not None:
                raise PortError(f"port {port} is leased to process {holder['pid']}")
            state["leases"][str(port)] = {
                "pid": pid,
                "start": process_start_time(pid),
                "bound": False,
                "at": time.time(),
            }
        return port

    def confirm(self, port: int) -> None:
        """Record that our server has bound the port: the lease is now final."""
        with self._registry() as state:
            lease = state["leases"].get(str(port))
            if lease is None:
                raise PortError(f"port {port} is not leased")
            lease["bound"] = True

    def release(self, port: int) -> None:
        """Give the port back; it is quarantined before anyone gets it again."""
        with self._registry() as state:
            if state["leases"].pop(str(port), None) is not None:
                state["quarantine"][str(port)] = time.time() + self.quarantine_s

    def leases(self) -> dict[int, dict]:
        """Live leases (port -> owner record), after reclaiming dead owners' leases."""
        with self._registry() as state:
            return {int(port): dict(lease) for port, lease in state["leases"].items()}

    def quarantined(self) -> dict[int, float]:
        with self._registry() as state:
            return {int(port): until for port, until in state["quarantine"].items()}
