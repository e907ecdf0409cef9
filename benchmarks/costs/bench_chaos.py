"""Chaos benchmark: 3DBall with 2 workers, ML-Agents' own PPO config, while faults keep coming
(``testkit/chaos.py``): a Unity player SIGKILLed every 30 s, a rollout worker SIGKILLed every
2 min, a player hung (SIGSTOP) every 90 s, the learner SIGKILLed once.

Two parts, in one invocation:

1. **Cost**, interleaved rounds of a clean run and a chaos run, each stopped (SIGTERM) once
   its mean reward reaches 90: time and steps to 90 with faults against without. 3DBall
   learns in well under 30 s here, so this part runs the schedule ``--compress`` times
   faster (default 10: a crash every 3 s, a hang every 9 s, a worker every 12 s, the
   learner at 5 s), or no fault would land before 90.
2. **Sustained**, one chaos run at the schedule's own pace for ``--sustained-s`` seconds
   (learner killed at 45 s): it must reach 90 and stay there while faults go on.

Every run reports: its exit code, any traceback, the faults injected against those
``summary.json`` counts, whether its sample ledger balances, and the processes of the run
that outlived it.

    .venv/bin/python -m benchmarks.costs.bench_chaos [--rounds 3] [--sustained-s 360]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import psutil

from benchmarks.common import RESULTS, ROOT, machine, mlagents_config
from testkit.chaos import ChaosDriver, Fault, issue_schedule  # not installed: run from the root

CONFIG = mlagents_config("ppo/3DBall.yaml")
REWARD = re.compile(r"Step: (\d+)\. .*Mean Reward: ([\d.]+)\.")
MARK = "UNITY_ROLLOUT_BENCH_RUN"


def marked(marker: str) -> list[psutil.Process]:
    found = []
    for process in psutil.process_iter():
        try:
            if process.environ().get(MARK) == marker:
                found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, ProcessLookupError):
            continue
    return found


def run(schedule: list[Fault], seconds: float, stop_at_90: bool, timeout_wait: int) -> dict:
    """One ``unity-rollout train``; the reward summaries it printed, as (s, step, reward)."""
    results, marker = Path(tempfile.mkdtemp(prefix="chaos-")), uuid.uuid4().hex
    command = [sys.executable, "-m", "driver.cli", "train", "--no-progress", "--config"]
    command += [str(CONFIG), "--results-dir", str(results), "--max-steps", "100000000"]
    command += ["--max-seconds", str(seconds), "--timeout-wait", str(timeout_wait)]
    started = time.monotonic()
    driver = subprocess.Popen(
        command,
        cwd=ROOT,
        env={**os.environ, MARK: marker},
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[tuple[float, str]] = []

    def read() -> None:
        assert driver.stdout is not None
        for line in driver.stdout:
            lines.append((time.monotonic() - started, line.rstrip("\n")))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()

    def training() -> bool:
        return any(REWARD.search(text) for _, text in list(lines))

    with ChaosDriver(driver.pid, schedule, seed=len(schedule), ready=training) as chaos:
        while driver.poll() is None:
            reached = [m for _, text in lines if (m := REWARD.search(text)) and float(m[2]) >= 90]
            if stop_at_90 and reached:
                driver.send_signal(signal.SIGTERM)
                break
            time.sleep(0.2)
        driver.wait(timeout=seconds + 300)
    reader.join(timeout=10)
    deadline = time.monotonic() + 60
    while (left := marked(marker)) and time.monotonic() < deadline:
        time.sleep(0.5)
    for process in left:
        process.kill()
    log = results / "output.log"
    log.write_text("".join(f"{t:8.1f}  {text}\n" for t, text in lines))
    summaries = [(t, int(m[1]), float(m[2])) for t, text in lines if (m := REWARD.search(text))]
    first = next(((t, s) for t, s, r in summaries if r >= 90), (None, None))
    summary_file = results / "run" / "summary.json"
    summary = json.loads(summary_file.read_text()) if summary_file.exists() else {}
    after = [r for t, _, r in summaries if first[0] is not None and t >= first[0]]
    return {
        "exit": driver.returncode,
        "traceback": any("Traceback" in text for _, text in lines),
        "orphans": len(left),
        "seconds_to_90": None if first[0] is None else round(first[0], 1),
        "steps_to_90": first[1],
        "summaries_after_90": len(after),
        "at_90_after": sum(r >= 90 for r in after),
        "min_after_90": min(after, default=None),
        "injected": {
            k: chaos.count(k) for k in ("kill-player", "hang-player", "kill-worker", "kill-learner")
        },
        "faults": summary.get("faults"),
        "ledger": summary.get("ledger", {}).get("dropped"),
        "ledger_balanced": summary.get("ledger", {}).get("balanced"),
        "steps": summary.get("steps"),
        "log": str(log),
    }


def compressed(factor: float) -> list[Fault]:
    return [
        Fault(f.kind, f.first_s / factor, f.every_s / factor, f.times)
        for f in issue_schedule(600.0, 50.0)
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--compress", type=float, default=10.0)
    parser.add_argument("--sustained-s", type=float, default=360.0)
    parser.add_argument("--timeout-wait", type=int, default=10)
    parser.add_argument("--out", default=str(RESULTS / "chaos.json"))
    args = parser.parse_args()
    report: dict = {"machine": machine(), "args": vars(args), "rounds": []}
    for round_ in range(args.rounds):
        order = ("clean", "chaos") if round_ % 2 == 0 else ("chaos", "clean")
        pair = {}
        for mode in order:
            schedule = compressed(args.compress) if mode == "chaos" else []
            pair[mode] = run(schedule, 600.0, True, args.timeout_wait)
            print(round_, mode, json.dumps(pair[mode]), flush=True)
        report["rounds"].append(pair)
    ratios = [
        p["chaos"]["seconds_to_90"] / p["clean"]["seconds_to_90"]
        for p in report["rounds"]
        if p["chaos"]["seconds_to_90"] and p["clean"]["seconds_to_90"]
    ]
    report["time_to_90_ratio_median"] = statistics.median(ratios) if ratios else None
    if args.sustained_s > 0:
        report["sustained"] = run(
            issue_schedule(args.sustained_s, 45.0), args.sustained_s, False, args.timeout_wait
        )
        print("sustained", json.dumps(report["sustained"]), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=2))
    print(json.dumps({"time_to_90_ratio_median": report["time_to_90_ratio_median"]}))


if __name__ == "__main__":
    main()
