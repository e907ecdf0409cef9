"""The node-wide port allocator: no duplicates under contention, quarantine, foreign
listeners skipped, dead owners' leases reclaimed, clear errors."""

from __future__ import annotations

import multiprocessing
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from rollout.environment.ports import (
    PortAllocator,
    PortError,
    PortRange,
    default_range,
    ephemeral_range,
)
from tests.waiting import wait_for

ROOT = Path(__file__).resolve().parents[2]


def _lease_many(registry: str, count: int, barrier, results) -> None:
    allocator = PortAllocator(PortRange(21000, 22999), registry)
    barrier.wait()
    results.put([allocator.lease() for _ in range(count)])
    barrier.wait()  # stay alive (owning the leases) until everyone is done


@pytest.mark.integration
def test_eight_processes_taking_200_leases_each_get_no_duplicates(tmp_path):
    context = multiprocessing.get_context("fork")
    barrier, results = context.Barrier(8), context.Queue()
    workers = [
        context.Process(target=_lease_many, args=(str(tmp_path), 200, barrier, results))
        for _ in range(8)
    ]
    for worker in workers:
        worker.start()
    try:
        ports = [port for _ in workers for port in results.get(timeout=120)]
    finally:
        for worker in workers:
            worker.join(timeout=60)
            if worker.is_alive():
                worker.kill()
    assert len(ports) == 1600
    assert len(set(ports)) == 1600
    assert all(21000 <= port <= 22999 for port in ports)


def test_released_port_is_quarantined_until_expiry(tmp_path):
    allocator = PortAllocator(PortRange(23500, 23500), tmp_path, quarantine_s=1.0)
    port = allocator.lease()
    allocator.release(port)
    assert port in allocator.quarantined()
    with pytest.raises(PortError, match="1 in quarantine"):
        allocator.lease()
    wait_for(lambda: port not in allocator.quarantined(), "the quarantine's end", 30)
    assert allocator.lease() == port


def test_port_held_by_a_foreign_listener_is_skipped(tmp_path):
    with socket.socket() as squatter:
        squatter.bind(("0.0.0.0", 0))
        squatter.listen()
        busy = squatter.getsockname()[1]
        allocator = PortAllocator(PortRange(busy, busy + 1), tmp_path)
        assert allocator.lease() == busy + 1
        with pytest.raises(PortError, match="1 held by other programs"):
            allocator.lease()


def test_lease_of_a_killed_owner_is_reclaimed(tmp_path):
    script = (
        "import sys\n"
        "from rollout.environment.ports import PortAllocator, PortRange\n"
        "allocator = PortAllocator(PortRange(23600, 23609), sys.argv[1])\n"
        "print(allocator.lease(), flush=True)\n"
        "sys.stdin.read()\n"  # it holds the lease until killed (or the test's end)
    )
    owner = subprocess.Popen(
        [sys.executable, "-c", script, str(tmp_path)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        port = int(owner.stdout.readline())
        allocator = PortAllocator(PortRange(23600, 23609), tmp_path)
        assert allocator.leases()[port]["pid"] == owner.pid
        os.kill(owner.pid, signal.SIGKILL)
        owner.wait(10)
        assert port not in allocator.leases()
        assert port in allocator.quarantined()  # freed by a death: it may be in TIME_WAIT
    finally:
        if owner.poll() is None:
            owner.kill()
            owner.wait()


def test_confirm_marks_the_lease_bound_and_release_frees_it(tmp_path):
    allocator = PortAllocator(PortRange(23700, 23709), tmp_path, quarantine_s=0.0)
    port = allocator.lease()
    assert allocator.leases()[port]["bound"] is False
    allocator.confirm(port)
    assert allocator.leases()[port]["bound"] is True
    allocator.release(port)
    assert allocator.leases() == {}
    with pytest.raises(PortError, match="not leased"):
        allocator.confirm(port)


def test_specific_port_lease_for_editor_mode(tmp_path):
    allocator = PortAllocator(PortRange(23800, 23809), tmp_path)
    assert allocator.lease_port(5004) == 5004
    with pytest.raises(PortError, match=f"leased to process {os.getpid()}"):
        allocator.lease_port(5004)


def test_exhaustion_names_the_range_and_how_to_widen_it(tmp_path):
    allocator = PortAllocator(PortRange(23900, 23901), tmp_path)
    allocator.lease()
    allocator.lease()
    with pytest.raises(PortError, match=r"no free port in 23900-23901.*UNITY_ROLLOUT_PORT_RANGE"):
        allocator.lease()


def test_default_range_avoids_ephemeral_and_ray_ports(monkeypatch):
    monkeypatch.delenv("UNITY_ROLLOUT_PORT_RANGE", raising=False)
    ports = default_range()
    low, high = ephemeral_range()
    assert ports.end < low or ports.start > high
    assert ports.start > 19999
    monkeypatch.setenv("UNITY_ROLLOUT_PORT_RANGE", "25000-25099")
    assert default_range() == PortRange(25000, 25099)
    monkeypatch.setenv("UNITY_ROLLOUT_PORT_RANGE", "oops")
    with pytest.raises(PortError, match="expected START-END"):
        default_range()
    with pytest.raises(PortError, match="1024 <= START"):
        PortRange(10, 20)
