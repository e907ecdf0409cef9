"""Training goes on while faults keep coming (the short form of benchmarks/costs/bench_chaos.py).

One ``unity-rollout train`` on 3DBall with 2 workers takes, one after the other, each fault
once the run has shown it handled the one before: a player crash, a hung player, a killed
worker, a killed learner, another crash. Then it must reach a mean reward of 90 within a
budget of steps, stop gracefully on SIGTERM, show every fault in its output and in
``summary.json``, print no traceback and leave no process behind."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import threading
import time
import uuid
from pathlib import Path

import pytest

from testkit.chaos import ChaosDriver
from tests.helpers import assert_run_gone, kill_run, start_train_cli
from tests.waiting import poll_until

pytestmark = pytest.mark.integration

FAULTS_LINE = re.compile(
    r"^faults: unity restarts (\d+), worker restarts (\d+), learner restarts (\d+), "
    r"steps dropped ([\d,]+)$"
)
SUMMARY_LINE = re.compile(r"Step: (\d+)\. .*Mean Reward: ([\d.]+)\.")
STEPS_TO_RECOVER = 400_000  # after the last fault, to a mean reward of 90 (it takes ~100k)
SAFETY_S = 600  # a safety stop only: the budget above is in steps


class Output:
    """The run's output lines, read on a thread as they come."""

    def __init__(self, process: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(process,), daemon=True)
        self._thread.start()

    def _read(self, process: subprocess.Popen) -> None:
        assert process.stdout is not None
        for line in process.stdout:
            self.lines.append(line.rstrip("\n"))

    def faults(self) -> tuple[int, int, int]:
        found = [m for line in self.lines if (m := FAULTS_LINE.match(line))]
        return tuple(int(g) for g in found[-1].groups()[:3]) if found else (0, 0, 0)

    def summaries(self) -> list[tuple[int, float]]:
        found = [m for line in self.lines if (m := SUMMARY_LINE.search(line))]
        return [(int(m[1]), float(m[2])) for m in found]

    def text(self) -> str:
        return "\n".join(self.lines[-60:])

    def finish(self) -> None:
        """Every line the run wrote: its stdout has closed (the run has ended)."""
        self._thread.join(timeout=60)


def wait_until(condition, what: str, output: Output, driver: subprocess.Popen, started: float):
    def met() -> bool:
        assert driver.poll() is None, f"the run ended while waiting for {what}:\n{output.text()}"
        return condition()

    left = SAFETY_S - (time.monotonic() - started)
    assert poll_until(met, left), f"{what}: safety stop\n{output.text()}"


def test_training_goes_on_while_faults_keep_coming(tmp_path):
    marker = uuid.uuid4().hex
    driver = start_train_cli(
        marker,
        *("--results-dir", str(tmp_path), "--max-steps", "100000000"),
        # a hung player is found within timeout_wait: 20 s instead of mlagents' 60 keeps
        # the hang short (a player slow to connect is retried under the restart policy)
        *("--timeout-wait", "20"),
    )
    output, started = Output(driver), time.monotonic()
    chaos = ChaosDriver(driver.pid, [], seed=1)
    try:
        wait_until(lambda: output.summaries(), "training", output, driver, started)
        expected = [0, 0, 0]
        for kind, counter in [
            ("kill-player", 0),
            ("hang-player", 0),
            ("kill-worker", 1),
            ("kill-learner", 2),
            ("kill-player", 0),
        ]:
            injected = chaos.inject(kind)
            assert injected.pid is not None, f"no process for {kind}:\n{output.text()}"
            expected[counter] += 1
            want = tuple(expected)
            wait_until(
                lambda want=want: all(
                    seen >= w for seen, w in zip(output.faults(), want, strict=True)
                ),
                f"{kind} to show",
                output,
                driver,
                started,
            )
        after = len(output.summaries())
        last_step = max(step for step, _ in output.summaries())

        def recovered() -> bool:
            later = output.summaries()[after:]
            assert all(s < last_step + STEPS_TO_RECOVER for s, _ in later), output.text()
            return any(reward >= 90 for _, reward in later)

        wait_until(recovered, "a mean reward of 90 after the faults", output, driver, started)
        driver.send_signal(signal.SIGTERM)
        driver.wait(timeout=120)
    finally:
        kill_run(driver)
    output.finish()
    assert driver.returncode == 0, output.text()
    assert not any("Traceback" in line for line in output.lines), output.text()
    summary = json.loads((Path(tmp_path) / "run" / "summary.json").read_text())
    assert summary["interrupted"] == "SIGTERM"
    faults = summary["faults"]
    assert faults["unity_restarts"] >= 3, faults  # two crashes and a hang
    assert faults["worker_restarts"] >= 1, faults
    assert faults["learner_restarts"] == 1, faults
    assert faults["dropped_steps"] > 0, faults
    ledger = summary["ledger"]  # every step produced is delivered or dropped, with a reason
    assert ledger["balanced"], ledger
    assert ledger["produced"] == ledger["delivered"] + sum(ledger["dropped"].values())
    assert ledger["dropped"]["player failure"] > 0 and ledger["dropped"]["shutdown"] > 0
    assert ledger["dropped"]["worker death"] + ledger["dropped"]["learner restart"] > 0
    by_faults = sum(ledger["dropped"].values()) - ledger["dropped"]["shutdown"]
    assert by_faults == faults["dropped_steps"]
    assert set(ledger["workers"]) == {"0", "1"}
    assert_run_gone(marker)
