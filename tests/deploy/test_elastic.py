"""Elastic membership on a private two-node cluster (one CPU each): the second node is
stopped mid-run and a new one joins; the run goes on through both, collects from the new
node, and ends with a balanced ledger, its workers' players gone with their node."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import psutil
import pytest

from tests.deploy.raynodes import (
    CLUSTER_TEST_TIMEOUT_S,
    auth_env,
    cluster_processes,
    new_token,
    private_cluster,
    start_node,
    stop_node,
)
from tests.waiting import poll_until

pytestmark = [pytest.mark.integration, pytest.mark.timeout(CLUSTER_TEST_TIMEOUT_S)]

ROOT = Path(__file__).resolve().parents[2]
NODE = "UNITY_ROLLOUT_TEST_NODE"  # each worker node's own mark, inherited by its processes


def players(mark: str) -> list[psutil.Process]:
    return [p for p in cluster_processes(mark, NODE) if "unitysim" in " ".join(p.cmdline())]


class Driver:
    """tests/deploy/elastic_driver.py: its phase lines, read as they come."""

    def __init__(self, address: str, token: str, errors: Path) -> None:
        self.errors = errors
        self.process = subprocess.Popen(
            [sys.executable, "-m", "tests.deploy.elastic_driver", address],
            cwd=ROOT,
            env=auth_env(token),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=errors.open("w"),
            text=True,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.put(line)

    def phase(self, name: str, seconds: float = 180) -> dict[str, Any]:
        deadline = time.monotonic() + seconds  # a safety stop: the driver's phases end it
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=1)
            except queue.Empty:
                if self.process.poll() is not None:
                    break
                continue
            if line.startswith("{"):
                report = json.loads(line)
                assert report["phase"] == name, report
                return report
        raise AssertionError(f"no {name!r} phase: {self.errors.read_text()[-3000:]}")

    def go_on(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write("\n")
        self.process.stdin.flush()

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(timeout=30)


def test_workers_leave_with_a_stopped_node_and_join_with_a_new_one(tmp_path):
    token = new_token()
    first, second = uuid.uuid4().hex, uuid.uuid4().hex
    with private_cluster(token, [1, 1], [{}, {NODE: first}]) as nodes:
        driver = Driver(nodes[0].address, token, tmp_path / "driver.err")
        try:
            ready = driver.phase("ready")
            assert len(set(ready["nodes"].values())) == 2, ready  # a worker on each node
            assert players(first), "the second node runs a Unity player"

            stop_node(nodes[1])
            # players watch their worker and exit with it
            assert poll_until(lambda: not cluster_processes(first, NODE), 60), (
                f"processes outlived their node: {cluster_processes(first, NODE)}"
            )
            driver.go_on()
            shrunk = driver.phase("shrunk")
            assert shrunk["removed"] == 1, shrunk  # and collection went on without it

            nodes.append(
                start_node("w2", token, nodes[0].tag, nodes[0], 1, extra_env={NODE: second})
            )
            driver.go_on()
            grew = driver.phase("grew")
            on_new_node = set(grew["nodes"].values()) - set(ready["nodes"].values())
            assert len(on_new_node) == 1, (ready, grew)  # it collects on the new node
            # with the weights published by then, not from scratch
            assert grew["joined_with"] >= shrunk["version"] > 0, (shrunk, grew)
            assert players(second)

            done = driver.phase("done")
            assert driver.process.wait(timeout=60) == 0
        finally:
            driver.stop()
    ledger = done["ledger"]
    assert ledger["balanced"], ledger
    assert ledger["dropped"]["worker death"] <= 12 * 16  # one worker's rows in progress
    assert done["removed"] == 1 and done["added"] >= 2 and done["live"] == 2, done
    assert done["learner_steps"] == ledger["delivered"] > 0
    assert not cluster_processes(second, NODE)
