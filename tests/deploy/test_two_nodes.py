"""A two-node Ray cluster on one machine (two `ray start` processes, one CPU each, as the
manifests size nodes: one Unity instance per CPU): the rollout workers spread across both
nodes, and each node's port allocator (its own registry, as on separate machines) hands out
Unity ports independently, with no clash."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.deploy.raynodes import CLUSTER_TEST_TIMEOUT_S, auth_env, new_token, private_cluster

pytestmark = [pytest.mark.integration, pytest.mark.timeout(CLUSTER_TEST_TIMEOUT_S)]

ROOT = Path(__file__).resolve().parents[2]


def test_workers_spread_over_two_nodes_with_independent_port_registries(tmp_path):
    token = new_token()
    registries = {"head": tmp_path / "head-ports", "w1": tmp_path / "w1-ports"}
    node_env = [{"UNITY_ROLLOUT_RUNTIME_DIR": str(path)} for path in registries.values()]
    with private_cluster(token, [1, 1], node_env) as nodes:
        address = nodes[0].address
        env = auth_env(token)
        env["UNITY_ROLLOUT_RUNTIME_DIR"] = str(tmp_path / "driver-ports")  # must stay unused
        driver = subprocess.run(
            [sys.executable, "-m", "tests.deploy.two_node_driver", address, "2"]
            + [f"{name}={path}" for name, path in registries.items()],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=180,
        )
        assert driver.returncode == 0, (
            driver.stdout[-2000:] + driver.stderr[-6000:] + "".join(n.log() for n in nodes)
        )
    report = json.loads(driver.stdout.strip().splitlines()[-1])

    assert len(report["nodes"]) == 2 and sum(n["head"] for n in report["nodes"]) == 1
    workers = report["workers"]
    node_ids = {n["node_id"] for n in report["nodes"]}
    assert {w["node_id"] for w in workers} == node_ids, report  # one worker on each node
    assert report["segments"] >= 4 and report["unity_restarts"] == 0, report

    # Each node's registry holds exactly the port of the worker on that node.
    head_id = next(n["node_id"] for n in report["nodes"] if n["head"])
    port_on = {("head" if w["node_id"] == head_id else "w1"): w["port"] for w in workers}
    assert report["leases"] == {name: [port] for name, port in port_on.items()}, report
    assert len({w["port"] for w in workers}) == 2  # no clash between the two allocators
    assert not (tmp_path / "driver-ports" / "ports.json").exists()
