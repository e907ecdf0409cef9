"""Driver for tests/deploy/test_two_nodes.py, run as its own process against a private
cluster: N rollout workers on unitysim into a counting learner, then one JSON line on stdout
saying where each worker runs (Ray node id), its Unity port, and what each node's port
registry holds while the workers are alive.

    python -m tests.deploy.two_node_driver ADDRESS WORKERS NODE_DIR=REGISTRY_DIR ...
"""

from __future__ import annotations

import json
import sys

import ray
from ray.util.state import list_actors

from driver.training.counting_learner import CountingLearner
from learners.acting.factory import actor_factory
from rollout.environment.ports import PortAllocator
from rollout.environment.unity import UnityConfig
from rollout.serving.service import RolloutService, ServiceConfig


def main(argv: list[str]) -> int:
    address, workers, registries = argv[0], int(argv[1]), dict(a.split("=", 1) for a in argv[2:])
    ray.init(address=address, log_to_driver=False)
    try:
        nodes = [
            {"node_id": n["NodeID"], "head": "node:__internal_head__" in n["Resources"]}
            for n in ray.nodes()
            if n["Alive"]
        ]
        learner = ray.remote(CountingLearner).options(num_cpus=0).remote()
        config = ServiceConfig(
            UnityConfig("unitysim:3DBall", seed=0), num_workers=workers, horizon=16
        )
        with RolloutService(config, actor_factory, learner) as service:
            metrics = service.run(until=lambda m: m.segments >= 2 * workers)
            identities = ray.get([w.identity.remote() for w in service.workers])
            alive = list_actors(
                address=address,
                filters=[("class_name", "=", "RolloutWorker"), ("state", "=", "ALIVE")],
            )
            node_of_pid = {actor.pid: actor.node_id for actor in alive}
            leases = {
                name: sorted(PortAllocator(registry_dir=path).leases())
                for name, path in registries.items()
            }
            report = {
                "nodes": nodes,
                "workers": [{**i, "node_id": node_of_pid.get(i["pid"])} for i in identities],
                "leases": leases,
                "segments": metrics.segments,
                "unity_restarts": metrics.unity_restarts,
            }
        print(json.dumps(report), flush=True)
    finally:
        ray.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
