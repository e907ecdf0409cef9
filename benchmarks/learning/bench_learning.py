"""Learning benchmarks: ``unity-rollout train`` runs, each in its own process (fresh Ray,
local 2-core mode, 2 workers), read back from their TensorBoard files.

For each run: the mean episode reward over wall time and steps (a PNG curve in
``docs/img/``), the wall time at which it first reached its target, the final reward,
and the collection rate (agent steps/s) next to the learner's consumption rate (samples/s
through gradient updates): at 2 workers the learner must keep up.

    .venv/bin/python -m benchmarks.learning.bench_learning                # every run below
    .venv/bin/python -m benchmarks.learning.bench_learning --only 3DBall  # names starting so
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from benchmarks.common import ROOT, machine
from benchmarks.learning.trainer_runs import scalars


@dataclass(frozen=True)
class Run:
    name: str
    env: str
    config: str
    target: float
    seconds: float


RUNS = (
    Run("3DBall PPO (default train)", "unitysim:3DBall", "config/3DBall.yaml", 90.0, 600),
    Run("3DBall SAC", "unitysim:3DBall", "config/3DBall_sac.yaml", 90.0, 900),
    Run("3DBall IMPALA", "unitysim:3DBall", "config/3DBall_impala.yaml", 90.0, 600),
    Run("Basic PPO", "unitysim:Basic", "config/Basic.yaml", 0.9, 600),
    Run("GridWorld PPO", "unitysim:GridWorld", "config/GridWorld.yaml", 0.8, 900),
    Run("AnimalArena PPO", "unitysim:AnimalArena", "config/AnimalArena.yaml", 0.9, 300),
)


def run_one(run: Run, results: Path) -> dict:
    run_id = run.name.split()[0] + "-" + run.name.split()[1]
    command = [
        str(ROOT / ".venv/bin/unity-rollout"),
        "train",
        "--env",
        run.env,
        "--config",
        str(ROOT / run.config),
        "--results-dir",
        str(results),
        "--run-id",
        run_id,
        "--max-seconds",
        str(run.seconds),
        "--no-progress",
        "--force",
    ]
    started = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, check=False)
    run_dir = results / run_id
    if started.returncode != 0:
        return {"name": run.name, "error": started.stdout[-500:] + started.stderr[-500:]}
    rewards = scalars(run_dir, "Environment/Cumulative Reward")
    collect = [v for _, _, v in scalars(run_dir, "Perf/Agent Steps per Second")]
    learn = [v for _, _, v in scalars(run_dir, "Perf/Learner Samples per Second")]
    capacity = [v for _, _, v in scalars(run_dir, "Perf/Learner Samples per Busy Second")]
    busy = [v for _, _, v in scalars(run_dir, "Perf/Learner Busy Fraction")]
    start = min((t for t, _, _ in rewards), default=0.0)
    first_log = json.loads((run_dir / "summary.json").read_text())
    reached = next(((t - start, s) for t, s, v in rewards if v >= run.target), None)
    return {
        "name": run.name,
        "target": run.target,
        "seconds": first_log["seconds"],
        "steps": first_log["steps"],
        "final_reward": rewards[-1][2] if rewards else None,
        "best_reward": max((v for _, _, v in rewards), default=None),
        "reached_after_s": None if reached is None else round(reached[0], 1),
        "reached_at_step": None if reached is None else reached[1],
        "collect_steps_per_s": sum(collect) / len(collect) if collect else None,
        "learner_samples_per_s": sum(learn) / len(learn) if learn else None,
        "learner_samples_per_busy_s": sum(capacity) / len(capacity) if capacity else None,
        "learner_busy_fraction": sum(busy) / len(busy) if busy else None,
        "curve": [(round(t - start, 1), s, v) for t, s, v in rewards],
    }


def plot(result: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seconds = [t for t, _, _ in result["curve"]]
    rewards = [v for _, _, v in result["curve"]]
    figure, axis = plt.subplots(figsize=(5, 3), dpi=100)
    axis.plot(seconds, rewards, label="mean episode reward")
    axis.axhline(result["target"], color="grey", linestyle="--", label=f"target {result['target']}")
    axis.set_xlabel("wall time (s), 2 CPUs, 2 workers")
    axis.set_ylabel("Environment/Cumulative Reward")
    axis.set_title(result["name"], fontsize=10)
    axis.legend(loc="lower right", fontsize=8)
    figure.tight_layout()
    figure.savefig(out)
    plt.close(figure)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="run the runs whose name starts with this")
    parser.add_argument("--json", help="write the results here too")
    parser.add_argument("--images", default=str(ROOT / "docs" / "img"))
    args = parser.parse_args()
    images = Path(args.images)
    images.mkdir(parents=True, exist_ok=True)
    report = {"machine": machine(), "runs": []}
    with tempfile.TemporaryDirectory(prefix="bench-learning-") as results:
        for run in RUNS:
            if not run.name.startswith(args.only):
                continue
            print(f"running {run.name} for up to {run.seconds:.0f}s ...", file=sys.stderr)
            result = run_one(run, Path(results))
            if "error" not in result and result["curve"]:
                image = images / ("learning-" + run.name.split()[0] + "-" + run.name.split()[1])
                plot(result, image.with_suffix(".png"))
                result["plot"] = str(image.with_suffix(".png"))
            report["runs"].append(result)
            summary = {k: v for k, v in result.items() if k != "curve"}
            print(json.dumps(summary), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
