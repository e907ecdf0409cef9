"""A curriculum's lessons and rewards under mlagents-learn and ``unity-rollout train``, run
side by side (at once, one core's worth each on a 2-core machine), for a fixed wall time:
ML-Agents' ``WallJump_curriculum.yaml`` on unitysim's WallJump by default, whose lessons
move on training progress (10%, 30% and 50% of the behavior's ``max_steps``), so millions
of steps. A sequential round (``bench_vs_mlagents.py``) would take hours per side.

Both trainers get the same build, config, seed and 2 Unity instances. Read from each
run's TensorBoard events: per behavior, the step at which each lesson began
(``Environment/Lesson Number/<parameter>``), and the mean reward per bucket of steps
(``Environment/Cumulative Reward``), compared at the same steps.

    .venv/bin/python -m benchmarks.learning.bench_curriculum_vs_mlagents --seconds 4200 \\
        --work /tmp/cur
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
from pathlib import Path

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from benchmarks.common import machine, mlagents_config
from benchmarks.learning.bench_vs_mlagents import OURS_MLAGENTS, Case, anchor_run, our_run
from benchmarks.learning.trainer_runs import build_player


def series(folder: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar tag of one behavior's TensorBoard folder: (step, value) in order."""
    events = EventAccumulator(str(folder), size_guidance={"scalars": 0}).Reload()
    return {
        tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]
    }


def lessons(scalars: dict[str, list[tuple[int, float]]]) -> dict[str, dict[int, int]]:
    """Per curriculum parameter: the first summary step at each lesson number."""
    out: dict[str, dict[int, int]] = {}
    for tag, points in scalars.items():
        if tag.startswith("Environment/Lesson Number/"):
            firsts: dict[int, int] = {}
            for step, value in points:
                firsts.setdefault(int(value), step)
            out[tag.rsplit("/", 1)[1]] = firsts
    return out


def buckets(points: list[tuple[int, float]], size: int) -> dict[int, float]:
    """Mean of the summaries in each ``size``-step bucket, keyed by the bucket's end."""
    sums: dict[int, list[float]] = {}
    for step, value in points:
        sums.setdefault((step // size + 1) * size, []).append(value)
    return {end: round(sum(v) / len(v), 3) for end, v in sorted(sums.items())}


def read_run(root: Path) -> dict[str, dict]:
    """Per behavior folder of one run: its lessons, rewards and last step."""
    out = {}
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        if not list(folder.glob("events.out.tfevents.*")):
            continue
        scalars = series(folder)
        rewards = scalars.get("Environment/Cumulative Reward", [])
        out[folder.name] = {
            "lessons": lessons(scalars),
            "rewards": rewards,
            "last_step": max((s for points in scalars.values() for s, _ in points), default=0),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--config", default="ppo/WallJump_curriculum.yaml", help="<trainer>/<Name>.yaml"
    )
    parser.add_argument("--env", default="WallJump")
    parser.add_argument("--seconds", type=float, default=3600, help="wall time of both runs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bucket", type=int, default=500_000, help="steps per reward bucket")
    parser.add_argument(
        "--anchor", type=Path, default=Path(os.environ.get("MLAGENTS_ANCHOR", "/tmp/mlbench"))
    )
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-curriculum-"))
    work.mkdir(parents=True, exist_ok=True)
    case = Case(f"{args.env}-curriculum", args.env, args.config, None, (), args.seconds)
    build = build_player(args.env, work)
    config = mlagents_config(args.config)
    threads = [  # each run writes its own TensorBoard folders, read below
        threading.Thread(
            target=anchor_run, args=(case, args.seed, build, config, args.anchor, work, 31500)
        ),
        threading.Thread(
            target=our_run, args=(case, args.seed, build, config, OURS_MLAGENTS, work, None)
        ),
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    roots = {
        "mlagents-learn": work / "mlagents" / f"ml-{case.name}-{args.seed}",
        "ours": work / "ours" / f"ours-{case.name}-ml-{args.seed}",
    }
    result = {"machine": machine(), "config": args.config, "seconds": args.seconds, "runs": {}}
    for name, root in roots.items():
        behaviors = read_run(root) if root.is_dir() else {}
        result["runs"][name] = behaviors
        print(f"== {name} ({root})")
        for behavior, data in behaviors.items():
            print(f"  {behavior}: last step {data['last_step']:,}; lessons {data['lessons']}")
            per_bucket = buckets(data["rewards"], args.bucket)
            print(f"    mean reward per {args.bucket:,} steps: {per_bucket}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
