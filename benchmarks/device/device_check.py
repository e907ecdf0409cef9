"""The GPU and many-core checks of the learner, in one run of at most 8 minutes, one JSON.

For a machine with one GPU and many cores that already has the project's dependencies
(``../shared/offline-gpu/`` carries them to an offline one). Four stages, each a
benchmark of ``benchmarks/speed/`` in its own process under a hard timeout, in this order:

- ``learner``: ``speed/bench_learner.py`` on the CPU and the GPU (bfloat16 too), the 3DBall MLP
  and 84x84x3 cameras (``simple``, ``nature_cnn``): PPO samples/s, and the share of one
  update the GPU is busy (``--gpu-busy``). Goals: nature_cnn on the GPU >= 100,000; the MLP
  on the GPU >= the CPU's; the GPU busy >= 50% of an AnimalArena update (its config, the
  ``simple`` encoder: what the ``arena`` stage's learner runs).
- ``scale``: ``speed/bench_scale.py --delay-ms 0`` at ``--workers`` workers, counting and PPO
  learners (PPO on the GPU, waiting for each update as mlagents-learn does, and collecting
  through it: ``ppo+ahead``). Goal: PPO >= 0.8 of the counting learner's rate.
- ``arena``: ``unity-rollout train`` on AnimalArena, ``--workers`` workers, the learner on
  the GPU, ``nvidia-smi`` sampled every second (kept as a record: an update lasts tens of
  ms, too short for its samples). Goal: mean reward 0.9 within 25 s of launch.
- ``central``: ``speed/bench_central.py``: how many workers at 600 agent-steps/s one learner
  feeds. Goal: >= 256 (154k samples/s for 3DBall PPO).

A stage that fails or times out is recorded with its log's tail; the others run on.

    .venv/bin/python -m benchmarks.device.device_check [--out device-check.json]
    .venv/bin/python -m benchmarks.device.device_check --quick --device cpu   # a dry run, ~5 min
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from benchmarks.common import ROOT, machine
from benchmarks.learning.trainer_runs import scalars

BUDGET_S = 480


def run_stage(name: str, argv: list[str], timeout: float, out: Path) -> dict[str, Any]:
    """One benchmark process; its JSON (``--json``) if it wrote one, else its log's tail."""
    started = time.perf_counter()
    log = out.with_suffix(f".{name}.log")
    with log.open("w") as sink:
        try:
            code = subprocess.run(
                argv, cwd=ROOT, stdout=sink, stderr=subprocess.STDOUT, timeout=timeout
            ).returncode
        except subprocess.TimeoutExpired:
            code = "timeout"
    result: dict[str, Any] = {"exit": code, "seconds": round(time.perf_counter() - started, 1)}
    data = out.with_suffix(f".{name}.json")
    if data.exists():
        result["data"] = json.loads(data.read_text())
    else:
        result["log_tail"] = log.read_text()[-2000:]
    return result


class GpuSampler:
    """``nvidia-smi``'s SM utilization every second, in a thread (nothing without a GPU)."""

    def __init__(self) -> None:
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> GpuSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        query = ["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits"]
        while not self._stop.wait(1.0):
            try:
                line = subprocess.run(query, capture_output=True, text=True, timeout=5).stdout
                self.samples.append(float(line.split()[0]))
            except (OSError, ValueError, IndexError, subprocess.SubprocessError):
                return


def arena(args: argparse.Namespace, timeout: float, out: Path) -> dict[str, Any]:
    """AnimalArena with the learner on ``--device``: time to 0.9 from launch, GPU busy."""
    with tempfile.TemporaryDirectory() as results:
        argv = [
            sys.executable, "-m", "driver.cli", "train", "--env", "unitysim:AnimalArena",
            "--workers", str(args.workers), "--cpus", str(args.cpus), "--device", args.device,
            "--max-seconds", str(args.arena_seconds), "--results-dir", results,
            "--run-id", "arena", "--no-progress",
        ]  # fmt: skip
        launched = time.time()
        with GpuSampler() as gpu:
            result = run_stage("arena", argv, timeout, out)
        run_dir = Path(results) / "arena"
        tag = "Environment/Cumulative Reward"
        rewards = scalars(run_dir, tag) if run_dir.is_dir() else []
    reached = next((t - launched for t, _, v in rewards if v >= 0.9), None)
    busy = [s for s in gpu.samples if s > 0]
    return {
        **result,
        "seconds_to_0.9": None if reached is None else round(reached, 1),
        "final_reward": rewards[-1][2] if rewards else None,
        "gpu_sm_mean_of_nonzero_samples": sum(busy) / len(busy) if busy else None,
        "gpu_sm_samples": gpu.samples,
    }


def goals(stages: dict[str, Any], device: str) -> dict[str, Any]:
    """Each goal of the issue: the figure measured, the goal, and whether it is met (None
    where the stage gave no figure)."""

    def check(value: float | None, goal: float, at_most: bool = False) -> dict[str, Any]:
        met = None if value is None else (value <= goal if at_most else value >= goal)
        return {"value": value, "goal": goal, "met": met}

    best = stages["learner"].get("data", {}).get("best", {})
    cnn = [v for k, v in best.items() if "nature_cnn" in k and device in k]
    mlp_gpu = best.get(f"3DBall MLP | - | {device}")
    mlp_cpu = best.get("3DBall MLP | - | cpu")
    rates = {
        r["learner"]: r["agent_steps_per_s"]
        for r in stages["scale"].get("data", {}).get("best", [])
    }
    counting = rates.get("counting")
    ppo = max((rates[k] for k in ("ppo", "ppo+ahead") if k in rates), default=None)
    fed = stages["central"].get("data", {}).get("workers_fed", {})
    learner_fed = [v for k, v in fed.items() if k.startswith("learner ppo")]
    arena = stages["arena"]
    # the arena's learner: config/AnimalArena.yaml's simple encoder, float32, as in ``arena``
    busy = stages["learner"].get("data", {}).get("gpu_busy", {})
    arena_busy = busy.get(f"84x84x3 CNN | simple | {device}")
    return {
        "nature_cnn PPO samples/s": check(max(cnn) if cnn else None, 100_000),
        "3DBall MLP, GPU / CPU": check(mlp_gpu / mlp_cpu if mlp_gpu and mlp_cpu else None, 1.0),
        "PPO / counting learner at --workers": check(
            ppo / counting if ppo and counting else None, 0.8
        ),
        "AnimalArena seconds to 0.9": check(arena.get("seconds_to_0.9"), 25, at_most=True),
        "AnimalArena GPU busy while updating, %": check(
            None if arena_busy is None else 100 * arena_busy, 50
        ),
        "workers at 600 steps/s one PPO learner feeds": check(
            min(learner_fed) if learner_fed else None, 256
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("device-check.json"))
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--workers", type=int, default=14)
    parser.add_argument("--cpus", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--arena-seconds", type=int, default=60)
    parser.add_argument("--quick", action="store_true", help="small stages: a dry run")
    args = parser.parse_args()
    if args.quick:
        args.workers, args.arena_seconds = 2, 20
    out = args.out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    python = sys.executable
    devices = ["cpu"] if args.device == "cpu" else ["cpu", args.device]
    deadline = time.perf_counter() + BUDGET_S

    def left(share: float) -> float:
        return max(10.0, min(share, deadline - time.perf_counter() - 5))

    encoders = ["simple"] if args.quick else ["simple", "nature_cnn"]
    stages: dict[str, Any] = {"machine": machine(), "args": {**vars(args), "out": str(out)}}
    stages["learner"] = run_stage(
        "learner",
        [python, "-m", "benchmarks.speed.bench_learner", "--rounds", "1", "--updates", "2",
         "--devices", *devices, "--encoders", *encoders, "--gpu-busy",
         *([] if args.quick else ["--mixed-precision", args.device]),
         "--json", str(out.with_suffix(".learner.json"))],
        left(90 if args.quick else 120), out,
    )  # fmt: skip
    stages["scale"] = run_stage(
        "scale",
        [python, "-m", "benchmarks.speed.bench_scale", "--delay-ms", "0", "--workers",
         str(args.workers), "--learners", "counting", "ppo", "ppo+ahead", "--rounds", "1",
         "--seconds", "5" if args.quick else "10", "--warmup", "3", "--cpus", str(args.cpus),
         "--device", args.device, "--json", str(out.with_suffix(".scale.json"))],
        left(90 if args.quick else 120), out,
    )  # fmt: skip
    stages["arena"] = arena(args, left(args.arena_seconds + 40), out)
    stages["central"] = run_stage(
        "central",
        [python, "-m", "benchmarks.speed.bench_central", "--seconds", "4" if args.quick else "5",
         "--workers", "2" if args.quick else "8", "--build-rate", "50", "--agents", "12",
         "--cpus", str(args.cpus), "--device", args.device,
         "--json", str(out.with_suffix(".central.json"))],
        left(120 if args.quick else 170), out,
    )  # fmt: skip
    stages["goals"] = goals(stages, args.device)
    out.write_text(json.dumps(stages, indent=2))
    print(json.dumps({k: v.get("exit") for k, v in stages.items() if "exit" in v}))
    print(json.dumps(stages["goals"], indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
