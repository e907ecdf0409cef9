"""Driver for tests/deploy/test_elastic.py, run as its own process against a private
two-node cluster: an elastic service (``--workers auto``'s) on unitysim into a counting
learner pinned to the head. It prints a JSON line per phase and waits for the test between
them (a line on stdin): ``ready`` once a worker on each node delivered; ``shrunk`` once the
second node's worker left and collection went on without it; ``grew`` once a worker on the
node that joined again delivered; then ``done`` with the ledger and membership counts.

    python -m tests.deploy.elastic_driver ADDRESS
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
from ray.util.state import list_actors

from driver.training.counting_learner import CountingLearner
from learners.acting.factory import actor_factory
from rollout.environment.unity import UnityConfig
from rollout.serving.service import RolloutService, ServiceConfig

PHASE_S = 120.0  # a safety stop for each phase


def say(phase: str, **fields: Any) -> None:
    print(json.dumps({"phase": phase, **fields}), flush=True)


def delivering_nodes(service: RolloutService, address: str) -> dict[int, str]:
    """Worker index -> Ray node id, for live workers that delivered a collect."""
    assert service.membership is not None
    actors = list_actors(address=address, filters=[("class_name", "=", "RolloutWorker")])
    node_of_pid = {a.pid: a.node_id for a in actors if a.state == "ALIVE"}
    found = {}
    for index in service.membership.delivered - service.membership.retired:
        pid = ray.get(service.workers[index].identity.remote())["pid"]
        found[index] = node_of_pid.get(pid, "?")
    return found


def run_until(service: RolloutService, done: Any) -> None:
    deadline = time.monotonic() + PHASE_S
    while not done():
        if time.monotonic() > deadline:
            raise TimeoutError("phase did not finish")
        service.run(seconds=0.5, report_every=0.5)


def main(address: str) -> int:
    ray.init(address=address, log_to_driver=False)
    try:
        head = ray.get_runtime_context().get_node_id()
        learner = (
            ray.remote(CountingLearner)
            .options(num_cpus=0, scheduling_strategy=NodeAffinitySchedulingStrategy(head, False))
            .remote()
        )
        config = ServiceConfig(
            UnityConfig("unitysim:3DBall", seed=0),
            num_workers=1,  # the rest come from the cluster's size, as they would
            horizon=16,
            elastic=True,
            learner_cpus=0.0,
        )
        with RolloutService(config, actor_factory, learner) as service:
            membership = service.membership
            assert membership is not None
            run_until(service, lambda: len(set(delivering_nodes(service, address).values())) == 2)
            say("ready", nodes=delivering_nodes(service, address), head=head)
            sys.stdin.readline()  # the test stops the second node

            run_until(service, lambda: membership.removed >= 1)
            before = service.metrics.segments
            run_until(service, lambda: service.metrics.segments >= before + 5)
            say(
                "shrunk",
                removed=membership.removed,
                segments=service.metrics.segments,
                version=service.version,
            )
            sys.stdin.readline()  # the test starts the second node again

            run_until(service, lambda: any(i >= 2 for i in delivering_nodes(service, address)))
            joined = max(delivering_nodes(service, address))
            first = ray.get(service.workers[joined].metrics.remote()).policy_version
            say(
                "grew",
                nodes=delivering_nodes(service, address),
                added=membership.added,
                joined_with=first,
            )
            service.run(seconds=2.0)
            live = [service.workers[i] for i in service.live()]
        summary = ray.get(learner.summary.remote())
        say(
            "done",
            ledger=service.ledger.summary(),
            added=membership.added,
            removed=membership.removed,
            live=len(live),
            learner_steps=sum(summary["steps"].values()),
        )
    finally:
        ray.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
