"""Steps to a target reward, measured without Ray or timing: the learner and N collectors
(one Unity each) in one process, taking turns, as mlagents-learn's synchronous loop does.

The count does not depend on how busy the machine is, so candidate changes to the learner
can be compared one at a time on a shared machine: each seed runs in its own process (two
at a time), and summaries follow the config's ``summary_freq`` with mlagents-learn's rule
(mean return of the episodes finished since the previous summary). The wall-clock
comparison with mlagents-learn is ``bench_vs_mlagents.py``'s.

    .venv/bin/python -m benchmarks.learning.bench_steps \\
        tests/mlagents_configs/ppo/3DBall.yaml --env unitysim:3DBall --target 90 \\
        --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


def one_seed(args: argparse.Namespace) -> dict:
    """Train in this process until a summary reaches the target; the first such step."""
    import numpy as np
    import torch

    from learners.host.learner import CentralLearner
    from learners.trainer_config.parse import load_config
    from rollout.collecting.collector import Collector
    from rollout.environment.ports import PortAllocator
    from rollout.environment.unity import UnityConfig

    torch.manual_seed(args.seed)
    config = load_config(args.config)
    settings = list(config.behaviors.values()) or [config.default]
    every = args.summary_freq or min(s.summary_freq for s in settings)
    horizon = min(s.time_horizon for s in settings)
    learner = CentralLearner(config, seed=args.seed)
    allocator = PortAllocator(registry_dir=args.registry)
    collectors = [
        Collector(
            UnityConfig(args.env, seed=args.seed * 100 + i),
            learner.factory,
            horizon=horizon,
            worker=i,
            allocator=allocator,
        )
        for i in range(args.workers)
    ]
    summaries: list[tuple[int, float]] = []
    returns: list[float] = []
    next_summary, done = every, False
    _, wanted = learner.submit([])
    try:
        while not done:
            for collector in collectors:
                # as the service does: no more than the next on-policy update wants
                share = args.chunk if wanted is None else math.ceil(wanted / len(collectors))
                version, wanted = learner.submit(
                    collector.collect(min_steps=min(share, args.chunk))
                )
                for other in collectors:
                    if version > other.version:
                        other.load_weights(*learner.weights())
            for collector in collectors:
                for builder in collector.builders.values():
                    returns.extend(builder.episodes.drain().returns.tolist())
            steps = sum(learner.progress()["steps"].values())
            while steps >= next_summary and not done:
                mean = float(np.mean(returns)) if returns else float("nan")
                summaries.append((next_summary, mean))
                returns, next_summary = [], next_summary + every
                done = mean >= args.target or next_summary > args.max_steps
    finally:
        for collector in collectors:
            collector.close()
    reached = next((step for step, mean in summaries if mean >= args.target), None)
    return {"seed": args.seed, "reached": reached, "summaries": summaries}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config")
    parser.add_argument("--env", default="unitysim:3DBall")
    parser.add_argument("--target", type=float, default=90.0)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--workers", type=int, default=2, help="Unity instances")
    parser.add_argument("--max-steps", type=int, default=500_000)
    parser.add_argument("--summary-freq", type=int, default=0, help="0: the config's")
    parser.add_argument(
        "--chunk",
        type=int,
        default=1000,
        help="steps per collect call, at most (fewer when "
        "the learner's next update wants fewer, as in the service)",
    )
    parser.add_argument("--parallel", type=int, default=2, help="seeds run at a time")
    parser.add_argument("--json", help="write the results here too")
    parser.add_argument("--seed", type=int, help=argparse.SUPPRESS)  # one seed, in-process
    parser.add_argument("--registry", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.seed is not None:
        print(json.dumps(one_seed(args)))
        return 0
    results, queue = [], list(args.seeds)
    with tempfile.TemporaryDirectory(prefix="bench-steps-") as registry:
        while queue:
            batch, queue = queue[: args.parallel], queue[args.parallel :]
            children = [
                subprocess.Popen(
                    [
                        sys.executable,
                        "-m",
                        __spec__.name,
                        *sys.argv[1:],
                        "--seed",
                        str(seed),
                        "--registry",
                        registry,
                    ],
                    stdout=subprocess.PIPE,
                    text=True,
                )
                for seed in batch
            ]
            for child in children:
                out, _ = child.communicate()
                if child.returncode != 0 or not out.strip():
                    raise SystemExit(f"bench_steps: a seed's run failed (exit {child.returncode})")
                result = json.loads(out.strip().splitlines()[-1])
                print(
                    f"seed {result['seed']}: target {args.target} at step {result['reached']}",
                    flush=True,
                )
                results.append(result)
    reached = [r["reached"] for r in results if r["reached"] is not None]
    report = {
        "config": args.config,
        "target": args.target,
        "reached": [r["reached"] for r in results],
        "median": statistics.median(reached) if reached else None,
        "runs": results,
    }
    print(json.dumps({k: v for k, v in report.items() if k != "runs"}))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
