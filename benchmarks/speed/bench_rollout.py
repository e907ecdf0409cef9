"""Collection throughput, side by side in one run, on a unitysim environment (3DBall).

(a) the raw ``UnityEnvironment`` random-action loop; (b) torchrl's ``UnityMLAgentsWrapper``
taking random steps; (c) our collector with an MLP policy emitting ``[B, T]`` segments,
in-process; then the Ray service with 1 and 2 workers and a counting learner (scaling,
bytes per agent step and MB/s per worker to the learner, share of worker time outside
``collect``: transport and Ray overhead), and the workers' resident memory over the run.
With ``--env AnimalArena`` or ``GridWorld``: what camera observations cost on the way.

    .venv/bin/python -m benchmarks.speed.bench_rollout --seconds 20 [--json out.json]
    .venv/bin/python -m benchmarks.speed.bench_rollout --memory-minutes 10   # long memory run
"""

from __future__ import annotations

import mlagents_compat  # noqa: F401  (first: makes mlagents-envs import on modern protobuf)

# isort: split

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch
from mlagents_envs.environment import UnityEnvironment

from benchmarks.common import machine
from learners.acting.factory import actor_factory
from rollout.collecting.collector import Collector
from rollout.environment.ports import PortAllocator
from rollout.environment.unity import UnityConfig
from unitysim.launcher import build


def raw_loop(path: str, port: int, seconds: float) -> float:
    env = UnityEnvironment(file_name=path, base_port=port, no_graphics=True, timeout_wait=30)
    try:
        env.reset()
        behavior = next(iter(env.behavior_specs))
        spec = env.behavior_specs[behavior]

        def run(duration: float) -> tuple[int, float]:
            agents, started = 0, time.perf_counter()
            while time.perf_counter() - started < duration:
                decisions, _ = env.get_steps(behavior)
                env.set_actions(behavior, spec.action_spec.random_action(len(decisions)))
                env.step()
                agents += len(decisions)
            return agents, time.perf_counter() - started

        run(2.0)
        agents, elapsed = run(seconds)
        return agents / elapsed
    finally:
        env.close()


def torchrl_loop(path: str, port: int, seconds: float) -> float:
    from torchrl.envs import UnityMLAgentsWrapper

    unity = UnityEnvironment(file_name=path, base_port=port, no_graphics=True, timeout_wait=30)
    env = UnityMLAgentsWrapper(env=unity)
    try:
        group = next(iter(env.group_map))
        per_step = len(env.group_map[group])

        def run(duration: float) -> tuple[int, float]:
            """torchrl's own loop: ``rollout`` with its random policy, 100 steps a call."""
            steps, started = 0, time.perf_counter()
            while time.perf_counter() - started < duration:
                rollout = env.rollout(100, break_when_any_done=False)
                steps += rollout.batch_size[-1]
            return steps * per_step, time.perf_counter() - started

        run(2.0)
        agent_steps, elapsed = run(seconds)
        return agent_steps / elapsed
    finally:
        env.close()


def collector_loop(build_name: str, seconds: float, registry: str) -> dict:
    torch.set_num_threads(1)
    collector = Collector(
        UnityConfig(build_name),
        actor_factory,
        horizon=64,
        allocator=PortAllocator(registry_dir=registry),
    )
    try:
        collector.collect(512)
        started_steps = collector.snapshot().agent_steps
        started = time.perf_counter()
        while time.perf_counter() - started < seconds:
            collector.collect(512)
        elapsed = time.perf_counter() - started
        return {"agent_steps_per_s": (collector.snapshot().agent_steps - started_steps) / elapsed}
    finally:
        collector.close()


def service_run(build_name: str, workers: int, seconds: float, registry: str) -> dict:
    import psutil
    import ray

    from driver.training.counting_learner import CountingLearner
    from rollout.serving.service import RolloutService, ServiceConfig

    learner = ray.remote(CountingLearner).options(num_cpus=0).remote(bump_every=4)
    config = ServiceConfig(
        UnityConfig(build_name),
        num_workers=workers,
        horizon=64,
        worker_cpus=1.0 / workers,
        registry_dir=registry,
    )
    with RolloutService(config, actor_factory, learner) as service:
        service.run(seconds=8.0)  # start-up and warm-up
        first = service.refresh_metrics()
        steps0, collect0 = first.agent_steps, sum(w.seconds for w in first.workers)
        bytes0 = ray.get(learner.summary.remote())["bytes"]
        pids = [ray.get(w.identity.remote())["pid"] for w in service.workers]
        rss0 = [psutil.Process(p).memory_info().rss for p in pids]
        started = time.perf_counter()
        metrics = service.run(seconds=seconds)
        elapsed = time.perf_counter() - started
        bytes1 = ray.get(learner.summary.remote())["bytes"]
        rss1 = [psutil.Process(p).memory_info().rss for p in pids]
        collect_s = sum(w.seconds for w in metrics.workers) - collect0
    ray.kill(learner)
    return {
        "workers": workers,
        "agent_steps_per_s": (metrics.agent_steps - steps0) / elapsed,
        "bytes_per_s": (bytes1 - bytes0) / elapsed,
        # to the learner, per agent step and per worker (PNG cameras travel as uint8)
        "bytes_per_agent_step": (bytes1 - bytes0) / max(metrics.agent_steps - steps0, 1),
        "mb_per_s_per_worker": (bytes1 - bytes0) / elapsed / workers / 1e6,
        "outside_collect_share": max(0.0, 1.0 - collect_s / (elapsed * workers)),
        "policy_lag_mean": metrics.policy_lag_mean,
        "worker_rss_mb": [round(r / 2**20, 1) for r in rss1],
        "worker_rss_growth": [round(b / a - 1.0, 3) for a, b in zip(rss0, rss1, strict=True)],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--env", default="3DBall")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--memory-minutes", type=float, default=0.0)
    parser.add_argument(
        "--repeats",
        type=int,
        default=2,
        help="runs of each variant, interleaved; each keeps its best (other load on a noisy "
        "machine only ever slows a run down, so the best runs are the comparable ones)",
    )
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    builds = Path(tempfile.mkdtemp(prefix="bench-rollout-"))
    build(builds, [args.env])
    path = str(builds / args.env)
    registry = str(builds / "ports")
    allocator = PortAllocator(registry_dir=registry)
    results: dict = {"machine": machine(), "env": args.env}

    def leased(loop):
        def run() -> float:
            port = allocator.lease()
            try:
                return loop(path, port, args.seconds)
            finally:
                allocator.release(port)

        return run

    loops = {
        "a_raw": leased(raw_loop),
        "b_torchrl": leased(torchrl_loop),
        "c_ours": lambda: collector_loop(f"unitysim:{args.env}", args.seconds, registry)[
            "agent_steps_per_s"
        ],
    }
    # (a), (b), (c) in turn, ``repeats`` times; each keeps its best run (see below).
    side_by_side: dict[str, list[float]] = {name: [] for name in loops}
    for _ in range(args.repeats):
        for name, loop in loops.items():
            side_by_side[name].append(loop())
    best = {name: max(values) for name, values in side_by_side.items()}
    results["side_by_side_runs"] = {k: [round(v) for v in vs] for k, vs in side_by_side.items()}
    results["a_raw_agent_steps_per_s"] = best["a_raw"]
    results["b_torchrl_agent_steps_per_s"] = best["b_torchrl"]
    results["c_collector"] = {"agent_steps_per_s": best["c_ours"]}
    c = best["c_ours"]
    results["c_over_a"] = c / best["a_raw"]
    results["c_over_b"] = c / best["b_torchrl"]

    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        # Alternate 1 and 2 workers and keep each one's best run.
        runs: dict[int, list[dict]] = {1: [], 2: []}
        for _ in range(args.repeats):
            for workers in (1, 2):
                runs[workers].append(
                    service_run(f"unitysim:{args.env}", workers, args.seconds, registry)
                )
        one, two = (max(runs[w], key=lambda r: r["agent_steps_per_s"]) for w in (1, 2))
        results["service_1_worker"], results["service_2_workers"] = one, two
        results["service_runs"] = {
            w: [round(r["agent_steps_per_s"]) for r in rs] for w, rs in runs.items()
        }
        results["scaling_2_over_1"] = two["agent_steps_per_s"] / one["agent_steps_per_s"]
        if args.memory_minutes:
            results["memory_run"] = service_run(
                f"unitysim:{args.env}", 2, args.memory_minutes * 60, registry
            )
    finally:
        ray.shutdown()

    print(json.dumps(results, indent=2))
    print(
        f"\n| {results['machine']['date'][:10]} | {args.env} | "
        f"raw {results['a_raw_agent_steps_per_s']:.0f} | "
        f"torchrl {results['b_torchrl_agent_steps_per_s']:.0f} | ours {c:.0f} | "
        f"c/a {results['c_over_a']:.2f} | c/b {results['c_over_b']:.1f} | "
        f"2w/1w {results['scaling_2_over_1']:.2f} | "
        f"{two['bytes_per_agent_step']:.0f} B/agent-step, "
        f"{two['mb_per_s_per_worker']:.2f} MB/s per worker |"
    )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
