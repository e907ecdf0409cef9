"""A torchrl-style data collector over the rollout service, for users with their own loss
and training loop: Ray workers, each owning a Unity instance, act with the user's
``TensorDictModule`` on the CPU (``module_actor``); their rows reach the user as TensorDict
batches under torchrl's key names (``conventions``), and ``update_policy_weights_`` sends
the module's new weights to every worker once per version.

    collector = UnityCollector("unitysim:3DBall", policy, frames_per_batch=2048,
                               total_frames=100_000, behavior="3DBall")
    for batch in collector:          # TensorDict [2048]: observation, action, next, ...
        ...                          # the user's loss and optimizer
        collector.update_policy_weights_()
    collector.shutdown()

As torchrl's synchronous ``Collector``, workers hold back while the user trains: they collect
at most one batch ahead, acted by the weights of the last ``update_policy_weights_``
(``policy_version`` says which). Agents come and go as Unity sends them; rows end at an
episode's end or at ``horizon`` steps (``("next", "truncated")``), so a batch is a
sequence of whole trajectory pieces that torchrl's GAE reads as they are.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from typing import Any

import ray
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch.utils.data import IterableDataset

from batches import keys
from batches.segment import Segment
from rollout.environment.ports import PortRange
from rollout.environment.unity import UnityConfig
from rollout.serving.config import ServiceConfig
from rollout.serving.service import RolloutService
from torchrl_adapters.batch_queue import ALL, BatchQueue
from torchrl_adapters.conventions import BEHAVIOR, to_torchrl
from torchrl_adapters.module_actor import ModuleActorFactory

STEP_S = 1.0  # how long one routing step waits for a collect


class UnityCollector(IterableDataset):
    """``build``: a Unity build's path, or ``unitysim:<Env>``. ``policy``: one module for
    every behavior, or one per behavior name. ``behavior``: batches of this behavior only,
    exactly ``frames_per_batch`` steps each (without it: a TensorDict per behavior id, at
    least ``frames_per_batch`` steps in all). ``total_frames``: stop after this many
    (-1: never)."""

    def __init__(
        self,
        build: str,
        policy: TensorDictModuleBase | Mapping[str, TensorDictModuleBase],
        frames_per_batch: int,
        total_frames: int = -1,
        *,
        behavior: str | None = None,
        num_workers: int = 2,
        horizon: int = 64,
        seed: int = 0,
        worker_cpus: float = 1.0,
        unity: UnityConfig | None = None,
        port_range: PortRange | None = None,
        registry_dir: str | None = None,
    ) -> None:
        if frames_per_batch < 1:
            raise ValueError(f"frames_per_batch must be at least 1, not {frames_per_batch}")
        self.policy = policy
        self.frames_per_batch, self.total_frames = frames_per_batch, total_frames
        self.behavior = behavior
        self.unity = unity or UnityConfig(build, seed=seed)
        self.config = ServiceConfig(
            self.unity,
            num_workers=num_workers,
            horizon=horizon,
            worker_cpus=worker_cpus,
            port_range=port_range,
            registry_dir=registry_dir,
        )
        self.frames = 0  # yielded so far
        self._carry: TensorDict | None = None  # the steps a batch of one behavior left over
        self._service: RolloutService | None = None
        self._queue: Any = None
        self._own_ray = False

    # --- torchrl's collector interface --------------------------------------------------

    def __iter__(self) -> Iterator[TensorDict]:
        self._start()
        while self.total_frames < 0 or self.frames < self.total_frames:
            batch = self._next_batch()
            self.frames += batch.numel() if self.behavior else _steps(batch)
            yield batch

    def update_policy_weights_(
        self, policy_weights: TensorDictModuleBase | Mapping[str, Any] | None = None
    ) -> None:
        """Send ``policy_weights`` (a state dict, a module; None: the collector's policy
        as it is now) to every worker, once per worker; their next steps act with it."""
        source = self.policy if policy_weights is None else policy_weights
        if isinstance(source, torch.nn.Module):
            states = {ALL: _numpy(source.state_dict())}
        elif isinstance(source, Mapping) and all(
            isinstance(m, torch.nn.Module) for m in source.values()
        ):
            states = {name: _numpy(m.state_dict()) for name, m in source.items()}
        else:
            states = {ALL: _numpy(dict(source))}
        if self._queue is None:
            self._start()
        ray.get(self._queue.publish.remote(states))
        assert self._service is not None
        self._service.ask_learner()

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Unity's seed (each worker's player gets it, as mlagents-learn's ``--seed``);
        before the first batch only."""
        if self._service is not None:
            raise RuntimeError("set_seed: the workers are running; call it before iterating")
        self.unity = dataclasses.replace(self.unity, seed=seed)
        self.config = dataclasses.replace(self.config, unity=self.unity)
        return seed

    def state_dict(self) -> dict[str, Any]:
        return {"frames": self.frames}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.frames = int(state["frames"])

    def shutdown(self) -> None:
        """Stop every worker and its Unity instance; Ray too, if this collector started it."""
        if self._service is not None:
            self._service.stop()
            self._service = None
        if self._queue is not None:
            ray.kill(self._queue)
            self._queue = None
        if self._own_ray:
            ray.shutdown()
            self._own_ray = False

    def __enter__(self) -> UnityCollector:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.shutdown()

    # --- internals ----------------------------------------------------------------------

    def _start(self) -> None:
        if self._service is not None:
            return
        if not ray.is_initialized():
            cpus = max(2, int(self.config.num_workers * self.config.worker_cpus + 0.999))
            ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
            self._own_ray = True
        queue = ray.remote(BatchQueue).options(num_cpus=0)
        self._queue = queue.remote(self.frames_per_batch, self.behavior)
        factory = ModuleActorFactory(self.policy)
        self._service = RolloutService(self.config, factory, self._queue)
        self._service.start()

    def _next_batch(self) -> TensorDict:
        assert self._service is not None
        while (segments := ray.get(self._queue.take.remote())) is None:
            self._service.step(STEP_S)
        self._service.ask_learner()  # its demand is back: the next batch's collects start
        by_behavior: dict[str, list[Segment]] = {}
        for segment in segments:
            by_behavior.setdefault(segment.behavior, []).append(segment)
        parts = {b: to_torchrl(Segment.concat(s).to_tensordict()) for b, s in by_behavior.items()}
        if self.behavior is None:
            return TensorDict(parts, batch_size=[])
        rows = [self._carry] if self._carry is not None else []
        rows += [td.exclude(BEHAVIOR) for td in parts.values()]
        batch = torch.cat(rows) if len(rows) > 1 else rows[0]
        batch, self._carry = batch[: self.frames_per_batch], batch[self.frames_per_batch :]
        if not len(self._carry):
            self._carry = None
        elif not bool(batch[-1][keys.NEXT, keys.DONE]):  # a row cut here: bootstrap, as
            batch[keys.NEXT, keys.DONE][-1] = True  # at a horizon cut
            batch[keys.NEXT, keys.TRUNCATED][-1] = True
            if (cuts := batch.get((keys.NEXT, keys.CUT), None)) is not None:
                cuts[-1] = True
        return batch


def _steps(batch: TensorDict) -> int:
    return sum(batch[name].numel() for name in batch.keys())  # noqa: SIM118 (iter: rows)


def _numpy(state: Mapping[str, Any]) -> dict[str, Any]:
    return {k: torch.as_tensor(v).detach().cpu().numpy().copy() for k, v in state.items()}
