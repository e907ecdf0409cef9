"""What ``--collect-ahead`` costs in samples: ``unity-rollout train`` on unitysim 3DBall
(``config/3DBall.yaml``), each seed once without and once with it, interleaved; each run
stops (SIGTERM) at its first summary with mean reward >= 90 and reports that summary's step
and wall time.

    .venv/bin/python benchmarks/bench_ahead.py --ahead 2400 --seeds 0 1 2 3 [--workers 2]
        [--delay-ms 0] [--json out.json]
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
import time
from pathlib import Path
from typing import Any

from machine import machine  # benchmarks/machine.py

ROOT = Path(__file__).resolve().parent.parent
REWARD = re.compile(r"Step: (\d+)\. Time Elapsed: [\d.]+ s\. Mean Reward: ([\d.-]+)\.")


def run(ahead: int, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    command = [sys.executable, "-m", "driver.cli", "train", "--no-progress", "--seed", str(seed)]
    command += ["--workers", str(args.workers), "--collect-ahead", str(ahead)]
    command += ["--results-dir", tempfile.mkdtemp(prefix="bench-ahead-")]
    command += ["--max-steps", str(args.max_steps), "--max-seconds", str(args.max_seconds)]
    env = {**os.environ, "UNITYSIM_DELAY_MS": str(args.delay_ms)}
    started = time.monotonic()
    driver = subprocess.Popen(
        command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    reached = None
    assert driver.stdout is not None
    for line in driver.stdout:
        match = REWARD.search(line)
        if match and reached is None and float(match[2]) >= 90:
            reached = {"step": int(match[1]), "seconds": round(time.monotonic() - started, 1)}
            driver.send_signal(signal.SIGTERM)  # stops with a checkpoint, exit 0
    return {"ahead": ahead, "seed": seed, "reached_90": reached, "exit": driver.wait()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--ahead", type=int, default=2400)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--delay-ms", type=float, default=0.0)
    parser.add_argument("--max-steps", type=int, default=300_000)
    parser.add_argument("--max-seconds", type=float, default=600.0, help="a safety stop")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    runs = []
    for seed in args.seeds:
        for ahead in (0, args.ahead):
            runs.append(run(ahead, seed, args))
            print(json.dumps(runs[-1]), flush=True)
    steps = {
        ahead: [r["reached_90"]["step"] for r in runs if r["ahead"] == ahead and r["reached_90"]]
        for ahead in (0, args.ahead)
    }
    medians = {a: statistics.median(s) if s else None for a, s in steps.items()}
    print(f"median steps to 90: {medians}")
    if all(medians.values()):
        print(f"with / without: {medians[args.ahead] / medians[0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps({"machine": machine(), "runs": runs, "medians": medians}))


if __name__ == "__main__":
    main()
