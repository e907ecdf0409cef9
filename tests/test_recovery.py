"""Recovery of a run whose driver or learner dies.

- ``unity-rollout train`` SIGKILLed mid-run leaves no process behind, and ``--resume`` (or
  a job entrypoint's ``--resume-if-exists``) continues from its last checkpoint with the
  step count, the weights version and the optimizer state intact.
- A learner actor SIGKILLed mid-run comes back from the last checkpoint by itself; the run
  says so, counts it in ``summary.json`` and goes on to its step budget.

What came after that checkpoint is lost: at most one checkpoint_interval."""

from __future__ import annotations

import json
import signal
import subprocess
import uuid
from pathlib import Path

import pytest
import yaml

from driver.options import TrainOptions
from driver.training.planner import plan
from learners.host import checkpoint
from learners.trainer_config.parse import CONFIG_DIR
from tests.helpers import assert_run_gone, kill_run, run_marked, start_train_cli
from tests.waiting import poll_until

BEHAVIOR = "3DBall?team=0"


def adam_steps(state: dict) -> int:
    """How many optimizer steps the behavior's Adam has taken (its state's ``step``)."""
    optimizer = state["behaviors"][BEHAVIOR]["algorithm"]["optimizer"]
    return int(max(float(p["step"]) for p in optimizer["state"].values()))


def write_config(results: Path, **settings: int) -> None:
    """The shipped 3DBall config with frequent checkpoints (and ``settings``)."""
    config = yaml.safe_load((CONFIG_DIR / "3DBall.yaml").read_text())
    config["behaviors"]["3DBall"].update({"checkpoint_interval": 2000, **settings})
    (results / "3DBall.yaml").write_text(yaml.safe_dump(config))


def wait_for_checkpoints(driver: subprocess.Popen, checkpoints: Path, count: int) -> None:

    def written() -> bool:
        assert driver.poll() is None, driver.communicate()[0][-2000:]
        return len(list(checkpoints.rglob("step-*.pt"))) >= count

    if not poll_until(written, 240):  # a safety stop: the budget is checkpoints
        kill_run(driver)  # and what the run said
        raise AssertionError(f"no checkpoint #{count}: {driver.communicate()[0][-3000:]}")


def start_train(results: Path, marker: str, *extra: str) -> subprocess.Popen:
    config = str(results / "3DBall.yaml")
    return start_train_cli(marker, "--results-dir", str(results), "--config", config, *extra)


@pytest.mark.integration
@pytest.mark.timeout(660)  # two safety stops: 240 s for checkpoints, 300 s for the resume
def test_a_sigkilled_driver_resumes_with_steps_version_and_optimizer(tmp_path):
    """Resumed as a retried job entrypoint would: ``--resume-if-exists`` (``--resume`` takes
    the same path, and tests/driver/test_train.py resumes a cleanly stopped run with it)."""
    # summaries every 2,000 steps: the resumed stretch prints several even when the workers'
    # episode counts reach the driver late (a summary with no finished episode prints nothing)
    write_config(tmp_path, summary_freq=2000)
    marker = uuid.uuid4().hex
    driver = start_train(tmp_path, marker, "--max-steps", "1000000")
    try:
        wait_for_checkpoints(driver, tmp_path / "run" / "checkpoints", 2)
        driver.kill()  # SIGKILL: no handler, no final checkpoint
        driver.wait(timeout=30)
    finally:
        kill_run(driver)
    # the driver's death takes every process of the run. Ray's agents (DashboardAgent,
    # RuntimeEnvAgent) go last: their raylet died by SIGKILL, not SIGTERM, so each first
    # tries to tell the (dead) GCS, and Ray gives that call 60 s (publish_error_to_driver)
    assert_run_gone(marker, seconds=90)
    assert not (tmp_path / "run" / "summary.json").exists()  # it really died mid-run

    last = checkpoint.load(tmp_path / "run")
    step, version, adam = int(last["step"]), int(last["version"]), adam_steps(last)
    assert step > 0 and version > 0 and adam > 0

    marker = uuid.uuid4().hex
    resumed = start_train(tmp_path, marker, "--resume-if-exists", "--max-steps", str(step + 6000))
    try:
        output, _ = resumed.communicate(timeout=300)
    finally:
        kill_run(resumed)
    assert resumed.returncode == 0, output[-2000:]
    assert_run_gone(marker)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    final = checkpoint.load(summary["checkpoint"])
    assert final["step"] == summary["steps"] >= step + 6000
    assert final["version"] > version  # the versions go on from the checkpoint's
    # Adam goes on from its saved moments and step count: a fresh optimizer would have
    # taken only the resumed run's steps, fewer than the checkpoint already had
    assert adam_steps(final) > adam
    steps_printed = [
        int(line.split("Step: ")[1].split(".")[0])
        for line in output.splitlines()
        if "Step: " in line
    ]
    assert steps_printed and min(steps_printed) > step, (steps_printed[:3], output[-3000:])


def test_resume_if_exists_starts_a_run_that_has_no_checkpoint(tmp_path):
    options = TrainOptions(results_dir=str(tmp_path), run_id="new", resume_if_exists=True)
    planned = plan(options)
    assert (planned.run_dir, planned.resume) == (tmp_path / "new", False)


@pytest.mark.integration
def test_a_killed_learner_comes_back_from_the_checkpoint_and_the_run_goes_on(tmp_path):
    write_config(tmp_path)
    marker = uuid.uuid4().hex
    driver = start_train(tmp_path, marker, "--max-steps", "16000")
    try:
        wait_for_checkpoints(driver, tmp_path / "run" / "checkpoints", 2)
        learners = [p for p in run_marked(marker) if "RayLearner" in " ".join(p.cmdline())]
        assert len(learners) == 1, [p.cmdline() for p in run_marked(marker)]
        at_kill = checkpoint.load(tmp_path / "run")
        learners[0].send_signal(signal.SIGKILL)
        output, _ = driver.communicate(timeout=300)
    finally:
        kill_run(driver)
    assert driver.returncode == 0, output[-3000:]
    assert "Traceback" not in output, output[-3000:]
    said = [line for line in output.splitlines() if "the learner died" in line]
    assert len(said) == 1 and "restored from step-" in said[0], output[-3000:]
    assert "faults: unity restarts 0, worker restarts 0, learner restarts 1" in output
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["faults"]["learner_restarts"] == 1
    assert summary["steps"] >= 16000
    assert summary["version"] > at_kill["version"]
    assert_run_gone(marker)
