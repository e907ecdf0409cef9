"""The ceilings of the central parts, fed from synthetic sources (no Unity while measured):

1. **Routing**: the driver (``RolloutService``) with N ``SyntheticWorker``s that answer every
   collect at once with a recorded 3DBall collect, into the counting learner: collects and
   submissions routed per second, agent steps per second, the driver's CPU.
2. **Ingestion**: the central learner (PPO ``config/3DBall.yaml``, IMPALA
   ``config/3DBall_impala.yaml``) taking recorded collects as fast as it can, in-process
   and as the Ray actor the service talks to: samples per second, and the share spent in
   updates.

From both, how many workers of a build at ``--build-rate`` exchanges/s with ``--agents``
agents each one driver and one learner can feed.

    .venv/bin/python -m benchmarks.speed.bench_central [--seconds 15] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil
import ray

from benchmarks.common import machine
from driver.training.counting_learner import CountingLearner
from learners.acting.factory import actor_factory, policy_factory
from learners.host.remote import learner_actor
from learners.trainer_config.parse import CONFIG_DIR, load_config
from rollout.collecting.collector import Collector
from rollout.environment.ports import PortAllocator
from rollout.environment.unity import UnityConfig
from rollout.serving.service import RolloutService, ServiceConfig
from testkit.synthetic import SyntheticWorker, replayed  # not installed: run from the root

UNITY = UnityConfig("unitysim:3DBall")
LEARNER_CONFIGS = {"ppo": "3DBall.yaml", "impala": "3DBall_impala.yaml"}
# the learners' max_steps: never reached (past their configs' own, 300k, a learner stops
# updating, and a GPU learner passes that within a window)
NO_STEP_LIMIT = 10**9


def routing(workers: int, seconds: float, registry: str) -> dict[str, Any]:
    learner = ray.remote(CountingLearner).options(num_cpus=0).remote(bump_every=4)
    config = ServiceConfig(UNITY, num_workers=workers, worker_cpus=0.01, registry_dir=registry)
    service = RolloutService(config, actor_factory, learner, ray.remote(SyntheticWorker))
    try:
        with service:
            service.run(until=lambda m: m.segments >= 4 * workers, report_every=0.5)
            summary0 = ray.get(learner.summary.remote())
            segments0, cpu0 = service.metrics.segments, psutil.Process().cpu_times()
            started = time.perf_counter()
            service.run(seconds=seconds)
            elapsed = time.perf_counter() - started
            summary1 = ray.get(learner.summary.remote())
            cpu1 = psutil.Process().cpu_times()
    finally:
        ray.kill(learner)
    steps = sum(summary1["steps"].values()) - sum(summary0["steps"].values())
    return {
        "workers": workers,
        "collects_per_s": (service.metrics.segments - segments0) / elapsed,
        "submits_per_s": (summary1["submissions"] - summary0["submissions"]) / elapsed,
        "agent_steps_per_s": steps / elapsed,
        "driver_cpu": (cpu1.user + cpu1.system - cpu0.user - cpu0.system) / elapsed,
    }


def record(kind: str, collects: int, registry: str) -> list[Any]:
    """Real collects of 512+ steps, acted by ``kind``'s own policy."""
    config = load_config(CONFIG_DIR / LEARNER_CONFIGS[kind])
    collector = Collector(
        UNITY, policy_factory(config), 64, 0, PortAllocator(registry_dir=registry)
    )
    try:
        return [collector.collect(512) for _ in range(collects)]
    finally:
        collector.close()


def renumbered(collected: Any, number: int, version: int) -> list[Any]:
    """A recorded collect as new: its own source number, acted by the learner's newest
    weights (as a worker keeping up would send it; PPO drops steps of older ones)."""
    return [replayed(segment, version, ("bench", number)) for segment in collected]


def ingestion_in_process(
    kind: str, recorded: list[Any], seconds: float, device: str = "cpu"
) -> dict[str, Any]:
    import torch

    from learners.host.devices import Compute
    from learners.host.learner import CentralLearner

    torch.set_num_threads(1)
    config = load_config(CONFIG_DIR / LEARNER_CONFIGS[kind])
    learner = CentralLearner(config, NO_STEP_LIMIT, torch_threads=1, compute=Compute.of(device))
    learner.prepare()
    number = 0
    while learner.stats.updates < 2:  # warm up: first update's allocations
        number += 1
        learner.submit(renumbered(recorded[number % len(recorded)], number, learner.version))
    stats0, steps0 = learner.progress()["stats"], sum(learner.progress()["steps"].values())
    started = time.perf_counter()
    while time.perf_counter() - started < seconds:
        number += 1
        learner.submit(renumbered(recorded[number % len(recorded)], number, learner.version))
    elapsed = time.perf_counter() - started
    stats, steps = learner.progress()["stats"], sum(learner.progress()["steps"].values())
    return {
        "learner": kind,
        "path": "in-process",
        "samples_per_s": (steps - steps0) / elapsed,
        "update_share": (stats.update_seconds - stats0.update_seconds) / elapsed,
        "updates": stats.updates - stats0.updates,
    }


def ingestion_actor(
    kind: str, recorded: list[Any], seconds: float, device: str = "cpu"
) -> dict[str, Any]:
    config = load_config(CONFIG_DIR / LEARNER_CONFIGS[kind])
    learner = learner_actor(config, NO_STEP_LIMIT, device=device)
    try:
        number, version, in_flight = 0, 0, []

        def send() -> None:
            nonlocal number
            number += 1
            collected = renumbered(recorded[number % len(recorded)], number, version)
            in_flight.append(learner.submit.remote(ray.put(collected)))

        while ray.get(learner.progress.remote())["stats"].updates < 2:
            send()
            if len(in_flight) >= 2:
                version = ray.get(in_flight.pop(0))[0]
        progress0 = ray.get(learner.progress.remote())
        started = time.perf_counter()
        while time.perf_counter() - started < seconds:
            send()
            if len(in_flight) >= 2:  # the service's learner_in_flight
                version = ray.get(in_flight.pop(0))[0]
        ray.get(in_flight)
        elapsed = time.perf_counter() - started
        progress = ray.get(learner.progress.remote())
    finally:
        ray.kill(learner)
    steps = sum(progress["steps"].values()) - sum(progress0["steps"].values())
    busy = progress["stats"].update_seconds - progress0["stats"].update_seconds
    return {
        "learner": kind,
        "path": "Ray actor",
        "samples_per_s": steps / elapsed,
        "update_share": busy / elapsed,
        "updates": progress["stats"].updates - progress0["stats"].updates,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--workers", type=int, nargs="+", default=[2, 4, 8])
    parser.add_argument("--build-rate", type=float, default=50.0, help="exchanges/s per build")
    parser.add_argument("--agents", type=int, default=12, help="agents per build")
    parser.add_argument("--cpus", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--device", default="cpu", help="the learner's: cpu, cuda, cuda:N")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    registry = tempfile.mkdtemp(prefix="bench-central-ports-")
    results: dict[str, Any] = {"machine": machine(), "routing": [], "ingestion": []}
    recorded = {kind: record(kind, 8, registry) for kind in LEARNER_CONFIGS}
    for kind in LEARNER_CONFIGS:
        ingested = ingestion_in_process(kind, recorded[kind], args.seconds, args.device)
        results["ingestion"].append(ingested)
        print(json.dumps(results["ingestion"][-1]), flush=True)
    ray.init(num_cpus=args.cpus, include_dashboard=False, log_to_driver=False)
    try:
        for kind in LEARNER_CONFIGS:
            ingested = ingestion_actor(kind, recorded[kind], args.seconds, args.device)
            results["ingestion"].append(ingested)
            print(json.dumps(results["ingestion"][-1]), flush=True)
        for n in args.workers:
            results["routing"].append(routing(n, args.seconds, registry))
            print(json.dumps(results["routing"][-1]), flush=True)
    finally:
        ray.shutdown()
    per_worker = args.build_rate * args.agents
    route = max(r["agent_steps_per_s"] for r in results["routing"])
    results["per_worker_steps_per_s"] = per_worker
    results["workers_fed"] = {
        "driver": route / per_worker,
        **{
            f"learner {r['learner']} ({r['path']})": r["samples_per_s"] / per_worker
            for r in results["ingestion"]
        },
    }
    print(json.dumps(results["workers_fed"], indent=1))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
