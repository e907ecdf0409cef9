"""What collecting past the learner's demand costs in samples: ``unity-rollout train`` on
unitysim 3DBall (``config/3DBall.yaml``), each seed once without ``--collect-ahead`` and once
with it, interleaved; each run stops (SIGTERM) at its first summary with mean reward >= 90
and reports that summary's step and wall time. ``--base-tree DIR``: instead, each seed once
with the code in DIR (a checkout of another commit) and once with this one, both with
``--collect-ahead`` N (0 by default): what a change of the service's own rule costs.

    .venv/bin/python -m benchmarks.learning.bench_ahead --ahead 2400 --seeds 0 1 2 3 [--workers 2]
        [--delay-ms 0] [--json out.json]
    .venv/bin/python -m benchmarks.learning.bench_ahead --base-tree /tmp/base --workers 16 \\
        --delay-ms 40
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

from benchmarks.common import ROOT, machine

REWARD = re.compile(r"Step: (\d+)\. Time Elapsed: [\d.]+ s\. Mean Reward: ([\d.-]+)\.")


def run(side: str, ahead: int, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """One training run; ``side``: "this" tree or "base" (``--base-tree``)."""
    tree = args.base_tree.resolve() if side == "base" else ROOT
    command = [sys.executable, "-m", "driver.cli", "train", "--no-progress", "--seed", str(seed)]
    command += ["--workers", str(args.workers), "--collect-ahead", str(ahead)]
    command += ["--results-dir", tempfile.mkdtemp(prefix="bench-ahead-")]
    command += ["--max-steps", str(args.max_steps), "--max-seconds", str(args.max_seconds)]
    env = {**os.environ, "UNITYSIM_DELAY_MS": str(args.delay_ms), "PYTHONPATH": str(tree)}
    started = time.monotonic()
    driver = subprocess.Popen(
        command, cwd=tree, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    reached = None
    assert driver.stdout is not None
    for line in driver.stdout:
        match = REWARD.search(line)
        if match and reached is None and float(match[2]) >= 90:
            reached = {"step": int(match[1]), "seconds": round(time.monotonic() - started, 1)}
            driver.send_signal(signal.SIGTERM)  # stops with a checkpoint, exit 0
    return {
        "side": side,
        "ahead": ahead,
        "seed": seed,
        "reached_90": reached,
        "exit": driver.wait(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--ahead", type=int, help="default: 2400, or 0 with --base-tree")
    parser.add_argument("--base-tree", type=Path, help="another commit's checkout, run beside")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--delay-ms", type=float, default=0.0)
    parser.add_argument("--max-steps", type=int, default=300_000)
    parser.add_argument("--max-seconds", type=float, default=600.0, help="a safety stop")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.base_tree:
        ahead = args.ahead or 0
        sides = {"base": ("base", ahead), "this": ("this", ahead)}
    else:
        ahead = 2400 if args.ahead is None else args.ahead
        sides = {"without": ("this", 0), "with": ("this", ahead)}
    runs = []
    for seed in args.seeds:
        for label, (side, steps_ahead) in sides.items():
            runs.append({"label": label, **run(side, steps_ahead, seed, args)})
            print(json.dumps(runs[-1]), flush=True)
    steps = {
        label: [r["reached_90"]["step"] for r in runs if r["label"] == label and r["reached_90"]]
        for label in sides
    }
    medians = {label: statistics.median(s) if s else None for label, s in steps.items()}
    print(f"median steps to 90: {medians}")
    first, second = sides
    if medians[first] and medians[second]:
        print(f"{second} / {first}: {medians[second] / medians[first]:.2f}")
    if args.json:
        args.json.write_text(json.dumps({"machine": machine(), "runs": runs, "medians": medians}))


if __name__ == "__main__":
    main()
