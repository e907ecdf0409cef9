"""What PPO's ``max_policy_lag`` does with many workers: train unitysim 3DBall
(``config/3DBall.yaml``) with N workers at a build's speed to a step budget, once for each
``max_policy_lag``, interleaved per seed; then run each run's policy without training
(``--inference``, one undelayed worker) and report the mean reward of the episodes it ends.

Why not steps to a reward: with many workers 3DBall's first long episodes end late (with 192
agents and episodes of 1,000 steps, near 200k steps in every run), so the summaries of a
training run say little about how good its policy is until then. The evaluation does.

``--base-tree DIR`` trains each seed once more with the code in DIR (a checkout of another
commit, its own config and defaults) beside this tree's default config; every evaluation
runs with this tree's code.

    .venv/bin/python -m benchmarks.learning.bench_policy_lag --lags 2 1000 --seeds 0 1 2 \\
        [--workers 16] [--delay-ms 40] [--steps 60000] [--json out.json]
    .venv/bin/python -m benchmarks.learning.bench_policy_lag --lags --base-tree /tmp/base \\
        --seeds 0 1 2
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

import yaml

from benchmarks.common import ROOT, machine
from benchmarks.learning.trainer_runs import scalars

SUMMARY = re.compile(r"Step: (\d+)\. Time Elapsed: [\d.]+ s\.(?: Mean Reward: ([\d.-]+)\.)?")
STALE = "Policy/Stale Steps Dropped"


def config_with_lag(lag: int | None, folder: Path, tree: Path = ROOT) -> Path:
    """``tree``'s ``config/3DBall.yaml``, with ``max_policy_lag`` set to ``lag`` if given."""
    config = yaml.safe_load((tree / "config" / "3DBall.yaml").read_text())
    if lag is not None:
        config["behaviors"]["3DBall"]["hyperparameters"]["max_policy_lag"] = lag
    path = folder / f"3DBall-{'base' if tree != ROOT else 'lag' + str(lag)}.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def train(
    config: Path, results: Path, seed: int, args: argparse.Namespace, tree: Path = ROOT
) -> dict[str, Any]:
    """Train with ``tree``'s code until the first summary at or past ``--steps`` (SIGTERM:
    a checkpoint, exit 0)."""
    command = [sys.executable, "-m", "driver.cli", "train", "--no-progress", "--seed", str(seed)]
    command += ["--config", str(config), "--workers", str(args.workers), "--run-id", "train"]
    command += ["--results-dir", str(results), "--max-seconds", str(args.max_seconds)]
    env = {**os.environ, "UNITYSIM_DELAY_MS": str(args.delay_ms), "PYTHONPATH": str(tree)}
    started, step = time.monotonic(), 0
    driver = subprocess.Popen(
        command, cwd=tree, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    assert driver.stdout is not None
    for line in driver.stdout:
        match = SUMMARY.search(line)
        if match and step < args.steps <= int(match[1]):
            step = int(match[1])
            driver.send_signal(signal.SIGTERM)
    return {"steps": step, "seconds": round(time.monotonic() - started, 1), "exit": driver.wait()}


def evaluate(config: Path, results: Path, args: argparse.Namespace) -> dict[str, Any]:
    """The trained policy, not trained further: mean of the evaluation's summaries."""
    command = [sys.executable, "-m", "driver.cli", "train", "--no-progress", "--seed", "999"]
    command += ["--config", str(config), "--workers", "1", "--run-id", "eval", "--inference"]
    command += ["--initialize-from", "train", "--results-dir", str(results)]
    command += ["--max-steps", str(args.eval_steps)]
    done = subprocess.run(
        command,
        cwd=ROOT,
        env={**os.environ, "UNITYSIM_DELAY_MS": "0"},
        capture_output=True,
        text=True,
        timeout=args.max_seconds,
    )
    rewards = [float(m[2]) for m in SUMMARY.finditer(done.stdout + done.stderr) if m[2]]
    return {"eval_reward": statistics.mean(rewards) if rewards else None, "summaries": len(rewards)}


def stale_fraction(results: Path) -> float | None:
    """The share of the training run's steps PPO dropped as too stale (its TensorBoard)."""
    points = scalars(results / "train", STALE)
    if not points:
        return None
    _, step, dropped = points[-1]
    return round(dropped / step, 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--lags", type=int, nargs="*", default=[2, 1000])
    parser.add_argument("--base-tree", type=Path, help="another commit's checkout, trained beside")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--workers", type=int, default=16)
    parser.add_argument("--delay-ms", type=float, default=40.0)
    parser.add_argument("--steps", type=int, default=60_000, help="training budget")
    parser.add_argument("--eval-steps", type=int, default=36_000)
    parser.add_argument("--max-seconds", type=float, default=600.0, help="a safety stop")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="bench-lag-"))
    # (label, max_policy_lag or None for the tree's default, tree)
    sides: list[tuple[str, int | None, Path]] = [(f"lag {lag}", lag, ROOT) for lag in args.lags]
    if args.base_tree:
        sides = [("base", None, args.base_tree.resolve()), ("this", None, ROOT), *sides]
    runs = []
    for seed in args.seeds:
        for label, lag, tree in sides:
            results = folder / f"{label.replace(' ', '')}-seed{seed}"
            config = config_with_lag(lag, folder, tree)
            run = {"side": label, "seed": seed, **train(config, results, seed, args, tree)}
            run |= {"stale": stale_fraction(results), **evaluate(config, results, args)}
            runs.append(run)
            print(json.dumps(run), flush=True)
    for label, _, _ in sides:
        rewards = [r["eval_reward"] for r in runs if r["side"] == label and r["eval_reward"]]
        median = statistics.median(rewards) if rewards else None
        print(f"{label}: evaluation reward median {median}, runs {rewards}")
    if args.json:
        args.json.write_text(
            json.dumps(
                {"machine": machine(), "args": vars(args) | {"json": str(args.json)}, "runs": runs},
                default=str,
            )
        )


if __name__ == "__main__":
    main()
