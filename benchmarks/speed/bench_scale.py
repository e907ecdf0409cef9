"""Scaling at real Unity speed: unitysim 3DBall answering every exchange ``--delay-ms`` late (as a
build at 1000/D exchanges per second), collected by 1, 2, 4, 8 and 16 Ray workers, once into the
counting learner (``driver/training/counting_learner.py``: routing only) and once into the real
central learner (PPO, ``config/3DBall.yaml``), once with the service's default (workers wait for
each update, as mlagents-learn's environments do, while their rows in progress fit in a buffer:
``rollout/serving/demand.py``) and once collecting through it (``ppo+ahead``: ``--collect-ahead`` of
one buffer, or ``--ahead`` steps).

The runs are interleaved: each round goes through every worker count, and at each count
both learners, so the machine's load falls on all of them alike; each keeps its best round.
For every run, over a steady window after start-up: agent-steps/s delivered to the learner,
the ratio to N times the 1-worker rate, policy lag, the learner's busy fraction, the
driver's CPU, the machine's CPU, and the workers' and players' resident memory. The result
goes to ``benchmarks/results/scaling.json`` (``--json F``: to F), which ``benchmarks/plots.py``
draws.

    .venv/bin/python -m benchmarks.speed.bench_scale --delay-ms 40 [--workers 1 2 4 8 16]
        [--rounds 2] [--seconds 20] [--json F]
    .venv/bin/python -m benchmarks.speed.bench_scale --memory-minutes 10 --workers 16   # memory
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil
import ray

from benchmarks.common import RESULTS, record, save_result
from driver.training.counting_learner import CountingLearner
from learners.acting.factory import actor_factory, policy_factory
from learners.host.remote import learner_actor
from learners.trainer_config.parse import CONFIG_DIR, load_config
from rollout.environment.unity import UnityConfig
from rollout.serving.service import RolloutService, ServiceConfig

# ppo+ahead: workers go on collecting through each update (``--collect-ahead``, one buffer)
LEARNERS = ("counting", "ppo", "ppo+ahead")


@dataclass(frozen=True)
class Window:
    """What a run's counters read at one moment."""

    at: float
    steps: int  # delivered to the learner
    lag_sum: int
    lag_count: int
    busy_s: float  # the learner's time in updates
    driver_cpu_s: float
    machine_cpu: Any  # psutil's cpu_times


def learner_counts(kind: str, learner: Any) -> tuple[int, float]:
    """(steps the learner took, seconds it spent updating)."""
    if kind == "counting":
        return sum(ray.get(learner.summary.remote())["steps"].values()), 0.0
    progress = ray.get(learner.progress.remote())
    return sum(progress["steps"].values()), progress["stats"].update_seconds


def read(kind: str, learner: Any, service: RolloutService) -> Window:
    steps, busy = learner_counts(kind, learner)
    metrics = service.metrics
    cpu = psutil.Process().cpu_times()
    return Window(
        time.perf_counter(),
        steps,
        metrics.policy_lag_sum,
        metrics.policy_lag_count,
        busy,
        cpu.user + cpu.system,
        psutil.cpu_times(),
    )


def machine_busy(before: Any, after: Any) -> float:
    """Cores in use between two psutil.cpu_times() readings."""
    idle = (after.idle + after.iowait) - (before.idle + before.iowait)
    total = sum(after) - sum(before)
    return (1.0 - idle / total) * (os.cpu_count() or 1) if total > 0 else 0.0


def memory_mb(service: RolloutService) -> tuple[list[float], list[float]]:
    """Resident MB of each worker process and of each worker's Unity player."""
    workers, players = [], []
    for worker in service.workers:
        identity = ray.get(worker.identity.remote())
        workers.append(psutil.Process(identity["pid"]).memory_info().rss / 2**20)
        if identity["player_pid"]:
            players.append(psutil.Process(identity["player_pid"]).memory_info().rss / 2**20)
    return workers, players


def one_run(
    kind: str, workers: int, args: argparse.Namespace, registry: str, on_minute: Any = None
) -> dict[str, Any]:
    """Start a service of ``workers`` into a ``kind`` learner, measure a steady window."""
    unity = UnityConfig("unitysim:3DBall", additional_args=("--sim-delay-ms", str(args.delay_ms)))
    if kind == "counting":
        learner = ray.remote(CountingLearner).options(num_cpus=0).remote(bump_every=4)
        factory = actor_factory
        horizon, ahead = 64, 0
    else:
        config = load_config(args.config)
        learner = learner_actor(config, max_steps=10**9, device=args.device)
        factory = policy_factory(config)
        settings = config.for_behavior("3DBall")
        horizon = settings.time_horizon
        if kind != "ppo+ahead":
            ahead = 0
        else:
            ahead = settings.hyperparameters.buffer_size if args.ahead is None else args.ahead
    service_config = ServiceConfig(
        unity,
        num_workers=workers,
        horizon=horizon,
        worker_cpus=min(1.0, args.cpus / workers),
        registry_dir=registry,
        collect_ahead=ahead,
    )
    started = time.perf_counter()
    try:
        with RolloutService(service_config, factory, learner) as service:
            # start-up: until every worker has delivered, then a settling stretch
            service.run(
                until=lambda m: len(m.workers) == workers and all(w.agent_steps for w in m.workers),
                report_every=0.5,
            )
            startup_s = time.perf_counter() - started
            service.run(seconds=args.warmup)
            first = read(kind, learner, service)
            memory = [memory_mb(service)]
            minutes = args.memory_minutes
            if minutes:
                for minute in range(int(minutes)):
                    service.run(seconds=60.0)
                    memory.append(memory_mb(service))
                    if on_minute:
                        on_minute(minute + 1, memory[-1])
            else:
                service.run(seconds=args.seconds)
            last = read(kind, learner, service)
            memory.append(memory_mb(service))
    finally:
        ray.kill(learner)
    elapsed = last.at - first.at
    worker_mb, player_mb = memory[-1]
    return {
        "learner": kind,
        "workers": workers,
        "startup_s": round(startup_s, 1),
        "window_s": round(elapsed, 1),
        "agent_steps_per_s": (last.steps - first.steps) / elapsed,
        "policy_lag_mean": (last.lag_sum - first.lag_sum)
        / max(last.lag_count - first.lag_count, 1),
        "learner_busy": (last.busy_s - first.busy_s) / elapsed,
        "driver_cpu": (last.driver_cpu_s - first.driver_cpu_s) / elapsed,
        "machine_cpu": machine_busy(first.machine_cpu, last.machine_cpu),
        "worker_rss_mb": round(max(worker_mb), 1),
        "player_rss_mb": round(max(player_mb), 1) if player_mb else None,
        "worker_rss_mb_by_time": [round(max(w), 1) for w, _ in memory],
    }


def table(best: dict[tuple[str, int], dict[str, Any]], counts: list[int]) -> list[str]:
    lines = [
        "| learner | workers | agent-steps/s | of linear | policy lag | learner busy | "
        "driver CPU | machine CPU (cores) | worker MB | player MB | start-up s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for kind in LEARNERS:
        one = best.get((kind, counts[0]))
        for n in counts:
            run = best.get((kind, n))
            if run is None:
                continue
            linear = run["agent_steps_per_s"] / (n / counts[0] * one["agent_steps_per_s"])
            run["of_linear"] = round(linear, 3)
            lines.append(
                f"| {kind} | {n} | {run['agent_steps_per_s']:,.0f} | {linear:.2f} | "
                f"{run['policy_lag_mean']:.2f} | {run['learner_busy']:.2f} | "
                f"{run['driver_cpu']:.2f} | {run['machine_cpu']:.2f} | "
                f"{run['worker_rss_mb']:.0f} | {run['player_rss_mb'] or 0:.0f} | "
                f"{run['startup_s']:.0f} |"
            )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--delay-ms", type=float, default=40.0, help="unitysim --sim-delay-ms")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    parser.add_argument("--learners", nargs="+", choices=LEARNERS, default=list(LEARNERS))
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=20.0, help="measured window per run")
    parser.add_argument("--warmup", type=float, default=5.0, help="after every worker delivered")
    parser.add_argument("--cpus", type=int, default=os.cpu_count() or 2, help="ray.init num_cpus")
    parser.add_argument("--config", type=Path, default=CONFIG_DIR / "3DBall.yaml")
    parser.add_argument("--device", default="cpu", help="the PPO learner's: cpu, cuda, cuda:N")
    parser.add_argument(
        "--memory-minutes",
        type=float,
        default=0.0,
        help="instead: one run per learner and worker count this long, memory each minute",
    )
    parser.add_argument("--ahead", type=int, help="ppo+ahead's steps ahead (default: a buffer)")
    parser.add_argument(
        "--json",
        type=Path,
        help=f"the result file (default: {RESULTS}/scaling.json; scaling-memory.json with "
        "--memory-minutes)",
    )
    args = parser.parse_args()
    if args.json is None:
        args.json = RESULTS / ("scaling-memory.json" if args.memory_minutes else "scaling.json")

    registry = tempfile.mkdtemp(prefix="bench-scale-ports-")
    question = (
        "Does the workers' memory stay flat over a long run?"
        if args.memory_minutes
        else "How does collection scale with workers, at a build's speed?"
    )
    results: dict[str, Any] = record(
        question, args={**vars(args), "config": str(args.config), "json": str(args.json)}
    )
    runs: list[dict[str, Any]] = []
    ray.init(num_cpus=args.cpus, include_dashboard=False, log_to_driver=False)
    try:
        rounds = 1 if args.memory_minutes else args.rounds
        for round_ in range(rounds):
            for n in args.workers:
                for kind in args.learners:
                    run = one_run(
                        kind,
                        n,
                        args,
                        registry,
                        lambda m, mem: print(
                            f"  minute {m}: worker MB {max(mem[0]):.0f}", flush=True
                        ),
                    )
                    run["round"] = round_
                    runs.append(run)
                    print(json.dumps(run), flush=True)
    finally:
        ray.shutdown()
    best: dict[tuple[str, int], dict[str, Any]] = {}
    for run in runs:
        key = (run["learner"], run["workers"])
        if key not in best or run["agent_steps_per_s"] > best[key]["agent_steps_per_s"]:
            best[key] = run
    lines = table(best, args.workers)
    print("\n".join(lines))
    results["runs"] = runs
    results["best"] = list(best.values())
    results["table"] = lines
    print(f"wrote {save_result(args.json, results)}")


if __name__ == "__main__":
    main()
