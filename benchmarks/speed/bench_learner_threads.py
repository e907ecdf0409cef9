"""The learner's torch threads: ``unity-rollout train`` to a step budget with
``--learner-threads 1`` against ``--learner-threads N`` (default N: the machine's cores,
the default of an on-policy run), interleaved, several rounds; reported per run: agent
steps per second from the run's ``summary.json``; per round: N threads / one thread.

    .venv/bin/python -m benchmarks.speed.bench_learner_threads --rounds 2 \\
        --case tests/mlagents_configs/ppo/3DBall.yaml unitysim:3DBall 60000 \\
        --case tests/mlagents_configs/poca/DungeonEscape.yaml unitysim:DungeonEscape 80000
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import ROOT, machine

CORES = len(os.sched_getaffinity(0))


def run(config: str, env: str, steps: int, extra: list[str], work: Path, name: str) -> dict:
    command = [
        str(ROOT / ".venv/bin/unity-rollout"),
        "train",
        "--config",
        config,
        "--env",
        env,
        "--max-steps",
        str(steps),
        "--workers",
        "2",
        "--no-progress",
        "--force",
        "--results-dir",
        str(work),
        "--run-id",
        name,
        "--learner-threads",
        *extra,
    ]
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - started
    if done.returncode != 0:
        sys.exit(f"{name} exited {done.returncode}: {done.stderr.strip().splitlines()[-1:]}")
    summary = json.loads((work / name / "summary.json").read_text())
    return {
        "steps": summary["steps"],
        "seconds": summary["seconds"],
        "steps_per_s": round(summary["steps"] / summary["seconds"], 1),
        "process_s": round(wall, 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--case", nargs=3, action="append", metavar=("CONFIG", "ENV", "STEPS"), required=True
    )
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--threads", type=int, default=CORES, help="against one thread")
    parser.add_argument("--json", help="write the results here too")
    args = parser.parse_args()
    variants = {"one thread": ["1"], "more": [str(args.threads)]}
    report: dict = {"machine": machine(), "threads": args.threads, "cases": []}
    with tempfile.TemporaryDirectory(prefix="bench-threads-") as tmp:
        for config, env, steps in args.case:
            rounds = []
            for number in range(args.rounds):
                order = list(variants) if number % 2 == 0 else list(reversed(variants))
                result = {}
                for variant in order:
                    name = f"{Path(config).stem}-{number}-{variant.replace(' ', '-')}"
                    result[variant] = run(
                        config, env, int(steps), variants[variant], Path(tmp), name
                    )
                ratio = result["more"]["steps_per_s"] / result["one thread"]["steps_per_s"]
                result["ratio"] = round(ratio, 2)
                print(Path(config).stem, number, json.dumps(result), flush=True)
                rounds.append(result)
            median = statistics.median(r["ratio"] for r in rounds)
            case = {"config": config, "steps": int(steps), "rounds": rounds, "median": median}
            report["cases"].append(case)
            print(f"{Path(config).stem}: {args.threads} threads / one, median {median}")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
