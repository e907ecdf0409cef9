"""The Ray cluster job, for real: a private head on loopback with token auth, the training
command submitted with `ray job submit` as deploy/README.md does it, its logs, its results;
a submit without (or with a wrong) token refused; every Ray listener on 127.0.0.1."""

from __future__ import annotations

import json
import subprocess
import uuid
from pathlib import Path

import pytest

from tests.deploy.raynodes import (
    CLUSTER_TEST_TIMEOUT_S,
    LOOPBACK,
    RAY,
    auth_env,
    listening_addresses,
    new_token,
)
from tests.deploy.raynodes import private_cluster as start_private_cluster

pytestmark = [pytest.mark.integration, pytest.mark.timeout(CLUSTER_TEST_TIMEOUT_S)]

JOB_MAX_STEPS = 2000


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """One private single-node cluster (2 CPUs: the local 2-core mode) for this module."""
    token = new_token()
    registry = tmp_path_factory.mktemp("ports")
    env = {"UNITY_ROLLOUT_RUNTIME_DIR": str(registry)}
    with start_private_cluster(token, [2], [env]) as nodes:
        yield {"token": token, "head": nodes[0], "registry": registry}


def job_cli(cluster: dict, args: list[str], token: str | None, home: Path | None = None, **kw):
    """``ray job <args[0]> --address <head> <args[1:]>`` as a separate process."""
    env = auth_env(token)
    if home is not None:
        env["HOME"] = str(home)  # no ~/.ray/auth_token to fall back on
    address = f"http://{LOOPBACK}:{cluster['head'].ports['dashboard']}"
    return subprocess.run(
        [RAY, "job", args[0], "--address", address, *args[1:]],
        env=env,
        capture_output=True,
        text=True,
        **kw,
    )


def test_job_submit_trains_on_unitysim(cluster, tmp_path):
    token, results = cluster["token"], tmp_path / "results"
    job_id = f"unity-rollout-{uuid.uuid4().hex[:8]}"
    entrypoint = ["unity-rollout", "train", "--max-steps", str(JOB_MAX_STEPS), "--address"]
    entrypoint += ["auto", "--no-progress", "--results-dir", str(results), "--run-id", "job"]
    submitted = job_cli(
        cluster, ["submit", "--submission-id", job_id, "--no-wait", "--", *entrypoint], token,
        timeout=60,
    )  # fmt: skip
    assert submitted.returncode == 0, submitted.stdout + submitted.stderr
    follow = job_cli(cluster, ["logs", "--follow", job_id], token, timeout=240)
    status = job_cli(cluster, ["status", job_id], token, timeout=60)
    assert "succeeded" in status.stdout + status.stderr, (
        status.stdout + status.stderr + "\n--- job logs:\n" + follow.stdout[-4000:]
    )
    logs = job_cli(cluster, ["logs", job_id], token, timeout=60).stdout
    assert "finished:" in logs and "steps" in logs, logs[-3000:]
    summary = json.loads((results / "job" / "summary.json").read_text())
    assert isinstance(summary["steps"], int) and summary["steps"] >= JOB_MAX_STEPS, summary
    assert list((results / "job" / "checkpoints").rglob("*.pt"))


def test_submit_without_token_is_refused(cluster, tmp_path):
    marker = f"refused-{uuid.uuid4().hex[:8]}"
    for token, message in [
        (None, "Missing authentication token"),
        (new_token(), "Invalid authentication token"),
    ]:
        refused = job_cli(
            cluster, ["submit", "--no-wait", "--", "echo", marker], token, home=tmp_path,
            timeout=60,
        )  # fmt: skip
        assert refused.returncode != 0
        assert message in refused.stdout + refused.stderr, refused.stderr[-2000:]
    listed = job_cli(cluster, ["list"], cluster["token"], timeout=60)
    assert listed.returncode == 0, listed.stderr[-2000:]
    assert marker not in listed.stdout  # nothing was submitted


def test_every_ray_port_binds_loopback(cluster):
    listening = listening_addresses(cluster["head"].tag)
    assert {"gcs_server", "raylet"} <= set(listening), listening
    addresses = [address for group in listening.values() for address in group]
    assert all(a.startswith((f"{LOOPBACK}:", f"::ffff:{LOOPBACK}:")) for a in addresses), listening
    assert f"{LOOPBACK}:{cluster['head'].ports['dashboard']}" in addresses  # the job API
