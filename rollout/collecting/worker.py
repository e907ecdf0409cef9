"""The rollout worker as a Ray actor: a thin shell around
:class:`rollout.collecting.collector.Collector`.

It owns exactly one Unity instance (one CPU by default, one torch thread). The service
calls ``collect(version, weights)``: weights arrive as an ObjectRef resolved by Ray, only
when a newer version exists (a self-play opponent's snapshot inside them as a reference
of its own, fetched once); segments go back as the call's result, an ObjectRef the
service hands to the learner without touching the data.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys

import ray
from ray.exceptions import RayError

from batches.contracts import ActorFactory, Snapshot, Weights
from batches.parameters import Assignment, Values, reseeded
from rollout.collecting.collector import Collector, CollectorMetrics
from rollout.collecting.horizons import Horizons
from rollout.collecting.ledger import Collected
from rollout.environment.ports import PortAllocator, PortRange
from rollout.environment.unity import UnityConfig

log = logging.getLogger(__name__)


class WeightsLost(RuntimeError):
    """This worker lacks the weights the service sent it: Ray restarted it in between."""


@ray.remote(num_cpus=1)
class RolloutWorker:
    def __init__(
        self,
        index: int,
        unity: UnityConfig,
        actor_factory: ActorFactory,
        horizon: int | Horizons,
        port_range: PortRange | None = None,
        registry_dir: str | None = None,
    ) -> None:
        if (torch := sys.modules.get("torch")) is not None:  # a factory that acts with torch
            torch.set_num_threads(1)  # one CPU per worker
        # Distinct seeds (else two workers replay the same episodes) and player logs.
        self.seed_offset = 1000 * index
        unity = dataclasses.replace(
            unity,
            seed=unity.seed + self.seed_offset,
            env_params=self._seeded(unity.env_params),
            log_folder=f"{unity.log_folder}/worker-{index}" if unity.log_folder else None,
            no_graphics=index != 0 if unity.no_graphics_monitor else unity.no_graphics,
        )
        allocator = PortAllocator(port_range, registry_dir)
        self.collector = Collector(unity, actor_factory, horizon, index, allocator)
        self._start_error: Exception | None = None
        self._assignment = 0  # the number of the environment parameters applied
        restarted = ray.get_runtime_context().was_current_actor_reconstructed
        try:
            self.collector.start(restarted)
        except Exception as error:  # said by the first collect: a failed __init__ would
            self._start_error = error  # have Ray restart the actor and launch again

    def collect(
        self,
        version: int,
        published: tuple[int, Weights] | None,
        min_steps: int,
        max_seconds: float | None = None,
        parameters: Assignment | None = None,
    ) -> Collected:
        """``published``: the learner's ``weights()`` result, (version, weights), or None
        when this worker already has the newest version. A restart that no call saw (the
        worker died while idle) shows here: the service would otherwise never resend weights.
        ``parameters``: the run's current lesson values, applied once (a restarted worker
        starts from the first lesson's and takes the current ones here)."""
        if self._start_error is not None:
            raise self._start_error
        if parameters is not None and parameters.number > self._assignment:
            self._assignment = parameters.number
            self.collector.set_parameters(self._seeded(parameters.values), parameters.reset)
        if published is None and self.collector.version < version:
            raise WeightsLost(f"worker has version {self.collector.version}, sent {version}")
        if published is not None and published[0] > self.collector.version:
            self.collector.load_weights(published[0], self._resolved(published[1]))
        return self.collector.collect(min_steps, max_seconds)

    def _resolved(self, weights: Weights) -> Weights:
        """Snapshots travel by reference: fetched here only when the collector lacks them.
        One whose learner died keeps the behavior on the policy it had (an opponent: its
        steps train nothing) until the restored learner's weights come."""
        out = dict(weights)
        for behavior, value in weights.items():
            if not isinstance(value, Snapshot) or self.collector.holds(value.key):
                continue
            if isinstance(value.state, ray.ObjectRef):
                try:
                    out[behavior] = Snapshot(value.key, ray.get(value.state))
                except RayError as error:
                    log.warning("%s: snapshot lost (%s); acting on with the last", behavior, error)
                    del out[behavior]
        return out

    def _seeded(self, values: Values) -> Values:
        """A sampler stream per worker (mlagents-learn gives every environment the same)."""
        return {key: reseeded(value, self.seed_offset) for key, value in values.items()}

    def metrics(self) -> CollectorMetrics:
        return self.collector.snapshot()

    def identity(self) -> dict[str, int | None]:
        """Process ids and port, for supervision and tests."""
        unity = self.collector.unity
        return {
            "pid": os.getpid(),
            "player_pid": unity.player_pid if unity.env is not None else None,
            "port": unity.port,
            "restarts": unity.restarts,
        }

    def close(self) -> Collected:
        return self.collector.close()
