"""What the real-Ray tests of workers and the service share: their port range, a service
config and a worker of their own, and the checks of what comes back."""

from __future__ import annotations

from batches import keys
from batches.specs import step_spec
from learners.acting.factory import actor_factory
from rollout.collecting.worker import RolloutWorker
from rollout.environment.ports import PortRange
from rollout.environment.unity import UnityConfig
from rollout.serving.service import ServiceConfig

PORTS = PortRange(24300, 24399)


def service_config(
    unity: UnityConfig, registry: str, workers: int = 2, horizon: int = 16, **options: int
) -> ServiceConfig:
    """Half a CPU per worker, the test port range and registry."""
    return ServiceConfig(
        unity,
        num_workers=workers,
        horizon=horizon,
        worker_cpus=0.5,
        port_range=PORTS,
        registry_dir=registry,
        **options,
    )


def start_worker(ray, registry: str, build: str, horizon: int = 16, **unity):
    worker = RolloutWorker.options(num_cpus=0.5, max_restarts=0).remote(
        0, UnityConfig(build, **unity), actor_factory, horizon, PORTS, registry
    )
    return worker


def collect(ray, worker, times: int) -> list:
    segments = []
    for _ in range(times):
        segments += [s.to_tensordict() for s in ray.get(worker.collect.remote(0, None, 1))]
    return segments


def stop_worker(ray, worker) -> None:
    ray.get(worker.close.remote())
    ray.kill(worker)


def check_spec(segment, specs) -> None:
    behavior = segment.get_non_tensor(keys.BEHAVIOR)
    spec = step_spec(specs[behavior]).expand(*segment.batch_size)
    assert spec.is_in(segment.exclude(*keys.METADATA)), behavior
