"""Private Ray clusters for the deploy tests: `ray start --block` processes of our own.

Other sessions run Ray on the same machine, so nothing here may touch them: no ``ray stop``,
no default ports. Each node gets explicit ports on 127.0.0.1
(``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` is Ray's switch that keeps the node IP, and so
every listener, on loopback), a short temp dir
of its own (Unix socket paths are limited to 107 bytes), token auth with a test-generated
token in the environment (``~/.ray/auth_token`` is never read or written), and a tag in the
environment that every process of the cluster inherits: stopping signals the node's process
group, then SIGKILLs whatever still carries the tag, and reports anything that survives.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import random
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import psutil

from driver.local_ray import DASHBOARD_WAIT, START_WAIT_S
from tests.helpers import free_port
from tests.waiting import poll_until

VENV_BIN = Path(sys.executable).parent
RAY = str(VENV_BIN / "ray")
CLUSTER_TAG = "UNITY_ROLLOUT_DEPLOY_CLUSTER"
NODE_TAG = "UNITY_ROLLOUT_DEPLOY_NODE"  # one node's own: what stopping that node alone kills
LOOPBACK = "127.0.0.1"

NODE_UP_S = 180  # a node's `ray start` up to "Ray runtime started": a safety stop
# A test that starts a private cluster: on a loaded machine each node may take starts for
# START_WAIT_S and one more of up to NODE_UP_S (Ray's own 30-s wait for the raylet to
# register ran out there), then the test itself: the suite's 300 s per test would stop it
# mid-start (pytest-timeout).
CLUSTER_TEST_TIMEOUT_S = 1500


def free_ports(count: int) -> list[int]:
    """``count`` distinct ports nothing listens on (outside the ephemeral range)."""
    return [free_port() for _ in range(count)]


def _is_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def worker_port_window(size: int = 64) -> tuple[int, int]:
    """A window of ``size`` free ports inside Ray's worker-port range (10002-19999)."""
    for _ in range(200):
        start = random.randrange(10002, 19999 - size)
        if all(_is_free(p) for p in range(start, start + size)):
            return start, start + size - 1
    raise RuntimeError("no free window of Ray worker ports")


def new_token() -> str:
    return secrets.token_hex(32)  # what `ray get-auth-token --generate` makes


def auth_env(token: str | None) -> dict[str, str]:
    """The environment of a Ray process or submitter with (or, for None, without) the token."""
    # Not the test session's tag either: Ray's helpers (client server, resource tracker) do
    # not look like Ray to tests/conftest.py; CLUSTER_TAG is this cluster's own leak check.
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith("RAY_") and k != "UNITY_ROLLOUT_TEST_SESSION"
    }
    env["PATH"] = f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}"
    if token is None:
        env["RAY_AUTH_MODE"] = "disabled"  # and no token anywhere: sends no credentials
    else:
        env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=token)
    return env


@dataclass
class RayNode:
    """One `ray start --block` node (its process group) of a private test cluster."""

    name: str
    process: subprocess.Popen
    temp_dir: Path
    log_path: Path
    tag: str  # the cluster's
    own: str  # this node's alone (NODE_TAG)
    ports: dict[str, int] = field(default_factory=dict)

    @property
    def address(self) -> str:
        """The GCS address other nodes and drivers join (a head's)."""
        return f"{LOOPBACK}:{self.ports['gcs']}"

    def log(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-4000:]
        except OSError:
            return ""

    def gcs_log(self, lines: int = 30) -> str:
        """The tail of a head's GCS server log: what it did while a node could not reach it."""
        tails = []
        for path in sorted(self.temp_dir.glob("session_latest/logs/gcs_server.*")):
            with contextlib.suppress(OSError):
                records = path.read_text(errors="replace").splitlines()
                text = [r for r in records if r.startswith("[")][-lines:]  # not its stats
                tails.append(f"--- {path.name}:\n" + "\n".join(text))
        return "\n".join(tails) or f"no GCS log under {self.temp_dir}"


def start_node(
    name: str,
    token: str,
    tag: str,
    head: RayNode | None = None,
    num_cpus: int = 1,
    extra_env: dict[str, str] | None = None,
    loopback: bool = False,
) -> RayNode:
    """Start a head (``head`` None) or a worker node of ``head``; returns once it is up. A node
    that did not come up is stopped and started again, as KubeRay restarts a pod's
    ``ray start``, at least once and until ``START_WAIT_S`` has passed: on two loaded cores a
    head's GCS has missed Ray's deadline for its node info, a worker node has waited on the
    head's GCS for a minute, and two starts of a joining node in a row have met Ray's
    deadline for its node info (busy run J2)."""
    args = (name, token, tag, head, num_cpus, extra_env, loopback)
    deadline = time.monotonic() + START_WAIT_S
    for attempt in itertools.count(1):
        try:
            return _start_node(*args)
        except RuntimeError:
            if attempt >= 2 and time.monotonic() >= deadline:
                raise
    raise AssertionError("unreachable")


def _start_node(
    name: str,
    token: str,
    tag: str,
    head: RayNode | None,
    num_cpus: int,
    extra_env: dict[str, str] | None,
    loopback: bool,
) -> RayNode:
    temp_dir = Path(tempfile.mkdtemp(prefix=f"ur-{name}-", dir="/tmp"))
    names = ["gcs", "dashboard", "client", "node_manager", "object_manager", "agent_grpc"]
    names += ["agent_http", "runtime_env_agent", "metrics", "autoscaler_metrics"]
    names += ["dashboard_metrics"]
    ports = dict(zip(names, free_ports(len(names)), strict=True))
    low, high = worker_port_window()
    ports.update(min_worker=low, max_worker=high)
    env = auth_env(token)
    if loopback:
        # Node IP 127.0.0.1, so every port on loopback: single-node clusters only (in this
        # mode Ray refuses a second node, and rewrites a 127.0.0.1 --address to the
        # machine's address anyway).
        env["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    env.update(
        TMPDIR=str(temp_dir),  # the dashboard's forkserver leaves its socket dir here
        AUTOSCALER_METRIC_PORT=str(ports["autoscaler_metrics"]),  # fixed 44217 by default
        DASHBOARD_METRIC_PORT=str(ports["dashboard_metrics"]),  # fixed 44227 by default
        # Ray gives the head's dashboard 60 s to come up; beside two busy processes it took
        # longer and `ray start` failed: as long as the safety stop below
        **{DASHBOARD_WAIT: str(START_WAIT_S)},
        **{CLUSTER_TAG: tag},
        **(extra_env or {}),
    )
    own = uuid.uuid4().hex
    env[NODE_TAG] = own
    command = [RAY, "start", "--block", "--disable-usage-stats", f"--num-cpus={num_cpus}"]
    command += [
        f"--node-ip-address={LOOPBACK}",
        f"--node-manager-port={ports['node_manager']}",
        f"--object-manager-port={ports['object_manager']}",
        f"--min-worker-port={low}",
        f"--max-worker-port={high}",
        f"--dashboard-agent-grpc-port={ports['agent_grpc']}",
        f"--dashboard-agent-listen-port={ports['agent_http']}",
        f"--runtime-env-agent-port={ports['runtime_env_agent']}",
        f"--metrics-export-port={ports['metrics']}",
        f"--temp-dir={temp_dir}",
        "--object-store-memory=200000000",
    ]
    if head is None:
        command += [
            "--head",
            f"--port={ports['gcs']}",
            "--include-dashboard=true",
            f"--dashboard-host={LOOPBACK}",
            f"--dashboard-port={ports['dashboard']}",
            f"--ray-client-server-port={ports['client']}",
        ]
    else:
        command.append(f"--address={head.address}")
    log_path = temp_dir / "ray-start.log"
    with log_path.open("w") as log:
        process = subprocess.Popen(
            command,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: we stop it and nothing else
        )
    node = RayNode(name, process, temp_dir, log_path, tag, own, ports)
    # Ray's own waits for its GCS and raylet are 60 s and more: this one is a safety stop
    try:
        poll_until(
            lambda: "Ray runtime started" in node.log() or process.poll() is not None, NODE_UP_S
        )
    except BaseException:  # the test's own safety stop: nothing of this node stays behind
        stop_nodes([node])
        raise
    if "Ray runtime started" not in node.log():
        failure = node.log()
        # this node's processes only: a worker node shares the cluster's tag with the head
        # it failed to join, which its second start needs alive
        stop_node(node, grace_s=5.0, alone=True)
        state = "" if head is None else f"\n{head_state(head)}"
        raise RuntimeError(f"ray start ({name}) did not come up:\n{failure}{state}")
    return node


def head_state(head: RayNode) -> str:
    """Whether the head and its GCS are alive, and what they last wrote: for a worker node
    that could not reach the GCS (``ray start --block`` reports a daemon of its that died)."""
    alive = "running" if head.process.poll() is None else f"exited {head.process.returncode}"
    return (
        f"{gcs_state(head.address)}\n--- head's ray start ({alive}):\n"
        f"{head.log()[-1500:]}\n{head.gcs_log()}"
    )


def gcs_state(address: str) -> str:
    """What holds the head's GCS port and the connections to it, for a worker node that
    could not reach it (beside the suite only, twice, with the test's driver still
    connected): a stopped or busy GCS, or a full accept queue, read differently."""
    port = int(address.rsplit(":", 1)[1])
    listeners, states = [], {}
    for conn in psutil.net_connections(kind="tcp"):
        if conn.status == psutil.CONN_LISTEN and conn.laddr and conn.laddr.port == port:
            listeners.append(f"{conn.laddr.ip}:{port} by {_describe(conn.pid)}")
        elif conn.raddr and conn.raddr.port == port:
            states[conn.status] = states.get(conn.status, 0) + 1
    held = "; ".join(listeners) or "nothing listens"
    return f"head GCS port {port}: {held}; connections to it by state: {states}"


def _describe(pid: int | None) -> str:
    if pid is None:
        return "an unknown process"
    try:
        process = psutil.Process(pid)
        times = process.cpu_times()
        return (
            f"{pid} {process.name()} ({process.status()}, cpu {times.user + times.system:.1f} s, "
            f"{process.num_threads()} threads)"
        )
    except psutil.Error:
        return f"{pid} (gone)"


def cluster_processes(tag: str, variable: str = CLUSTER_TAG) -> list[psutil.Process]:
    """Live (non-zombie) processes whose environment has ``variable`` = ``tag`` (the
    cluster's tag by default; a node's own, given in its ``extra_env``, for one node)."""
    found = []
    for process in psutil.process_iter(["pid", "status"]):
        if process.info["status"] == psutil.STATUS_ZOMBIE or process.pid == os.getpid():
            continue
        try:
            if process.environ().get(variable) == tag:
                found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, ProcessLookupError):
            continue
    return found


def stop_node(node: RayNode, grace_s: float = 10.0, alone: bool = False) -> None:
    """Stop one node of a live cluster as ``ray stop`` on its machine would (SIGTERM, then
    SIGKILL after ``grace_s``), leaving the others running; ``alone``: then also every
    process of this node that left its group."""
    _signal_group(node, signal.SIGTERM)
    try:
        node.process.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        _signal_group(node, signal.SIGKILL)
        node.process.wait(timeout=10)
    if alone:
        _signal_group(node, signal.SIGKILL)
        for process in cluster_processes(node.own, NODE_TAG):
            with contextlib.suppress(psutil.NoSuchProcess):
                process.kill()
        poll_until(lambda: not cluster_processes(node.own, NODE_TAG), 10)


def _signal_group(node: RayNode, signum: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(node.process.pid, signum)


def stop_nodes(nodes: list[RayNode], grace_s: float = 5.0) -> list[str]:
    """Stop the nodes (workers first): SIGTERM each group, SIGKILL what remains after
    ``grace_s``; returns descriptions of processes still alive after that (should be none)."""
    for node in reversed(nodes):
        _signal_group(node, signal.SIGTERM)
    tags = {node.tag for node in nodes}
    poll_until(lambda: not any(cluster_processes(t) for t in tags), grace_s)
    for node in nodes:
        _signal_group(node, signal.SIGKILL)
    for tag in tags:
        for process in cluster_processes(tag):  # e.g. a process that left the group
            with contextlib.suppress(psutil.NoSuchProcess):
                process.kill()
    for node in nodes:
        with contextlib.suppress(subprocess.TimeoutExpired):
            node.process.wait(timeout=10)
    poll_until(lambda: not any(cluster_processes(t) for t in tags), 10)  # the SIGKILLed
    left = []
    for tag in tags:
        for process in cluster_processes(tag):
            with contextlib.suppress(psutil.NoSuchProcess):
                left.append(f"{process.pid}: {' '.join(process.cmdline())[:160]}")
    by_path = [
        f"{p.pid}: {' '.join(p.info['cmdline'] or [])[:160]}"
        for p in psutil.process_iter(["pid", "cmdline", "status"])
        if p.info["status"] != psutil.STATUS_ZOMBIE
        and any(str(node.temp_dir) in arg for node in nodes for arg in p.info["cmdline"] or [])
    ]
    for node in nodes:  # a process that was dying may still have written into it
        poll_until(lambda d=node.temp_dir: _removed(d), 10)
    return left + [entry for entry in by_path if entry not in left]


@contextlib.contextmanager
def private_cluster(
    token: str, node_cpus: list[int], node_env: list[dict[str, str]] | None = None
) -> Iterator[list[RayNode]]:
    """A head plus ``len(node_cpus) - 1`` worker nodes; always stopped, and checked gone.
    A single node listens on 127.0.0.1 only; nodes of a multi-node cluster on the machine's
    address (as separate machines would), token auth protecting them."""
    tag = uuid.uuid4().hex
    nodes: list[RayNode] = []
    node_env = node_env or [{} for _ in node_cpus]
    try:
        try:
            _start_cluster(nodes, token, tag, node_cpus, node_env)
        except RuntimeError:
            # A worker node that waited twice on the head's GCS: the head itself is stuck
            # (seen once on two loaded cores). The whole cluster starts once more.
            left = stop_nodes(nodes)
            assert not left, f"processes of the private Ray cluster survived: {left}"
            nodes.clear()
            _start_cluster(nodes, token, tag, node_cpus, node_env)
        yield nodes
    finally:
        left = stop_nodes(nodes) if nodes else []
        assert not left, f"processes of the private Ray cluster survived: {left}"


def _start_cluster(
    nodes: list[RayNode],
    token: str,
    tag: str,
    node_cpus: list[int],
    node_env: list[dict[str, str]],
) -> None:
    """The head, then each worker node, appended to ``nodes`` as each comes up."""
    loopback = len(node_cpus) == 1
    head = start_node("head", token, tag, None, node_cpus[0], node_env[0], loopback)
    nodes.append(head)
    for index, cpus in enumerate(node_cpus[1:], start=1):
        nodes.append(start_node(f"w{index}", token, tag, head, cpus, extra_env=node_env[index]))


def listening_addresses(tag: str) -> dict[str, list[str]]:
    """Local addresses (ip:port) the cluster's processes listen on, by process name."""
    found: dict[str, list[str]] = {}
    for process in cluster_processes(tag):
        with contextlib.suppress(psutil.NoSuchProcess, psutil.AccessDenied):
            for conn in process.net_connections(kind="tcp"):
                if conn.status == psutil.CONN_LISTEN:
                    found.setdefault(process.name(), []).append(
                        f"{conn.laddr.ip}:{conn.laddr.port}"
                    )
    return found


def _removed(directory: Path) -> bool:
    shutil.rmtree(directory, ignore_errors=True)
    return not directory.exists()
