"""The policy factory the learner and every worker share: a behavior's actor, and its
initial weights drawn from the run's seed and the behavior's name, so both sides start
from the very same policy. Picklable without torch: the service ships it to workers,
and only a behavior that acts through the torch network (images, goal conditioning)
makes a worker load torch.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from mlagents_envs.base_env import BehaviorSpec

from batches.contracts import base_name
from learners.acting.numpy_images import ImageTooSmall
from learners.acting.numpy_policy import NumpyActor, acts_in_numpy, initial_weights
from learners.trainer_config.settings import NetworkSettings, RunConfig, TrainerSettings
from learners.trainer_config.trainer_types import trainer

if TYPE_CHECKING:
    from learners.networks.policies import ActorCritic, TorchActor


@dataclass(frozen=True)
class PolicyFactory:
    """Builds a behavior's policy the same way on the learner and in every worker, down
    to the initial weights (drawn from ``seed`` and the behavior's name): before the first
    update every worker acts with the very policy the learner will improve, as
    mlagents-learn's one policy does, so the first update's ratios start at 1.

    Picklable without torch, so the service ships it to workers; ``settings`` is keyed by
    the behavior name without ``?team=``, as in trainer configs.
    """

    settings: Mapping[str, NetworkSettings] = field(default_factory=dict)
    default: NetworkSettings = field(default_factory=NetworkSettings)
    seed: int = 0

    def settings_for(self, behavior: str) -> NetworkSettings:
        return self.settings.get(base_name(behavior), self.default)

    def _key(self, behavior: str) -> int:
        return zlib.crc32(f"{self.seed}/{behavior}".encode())

    def initial_weights(self, behavior: str, spec: BehaviorSpec) -> dict[str, np.ndarray]:
        """An image below its encoder's minimum size fails here, naming the behavior."""
        rng = np.random.default_rng(self._key(behavior))
        try:
            return initial_weights(spec, self.settings_for(behavior), rng)
        except ImageTooSmall as error:
            raise ImageTooSmall(f"behavior {base_name(behavior)} {error}") from None

    def network(self, behavior: str, spec: BehaviorSpec) -> ActorCritic:
        """The learner's ``ActorCritic`` (loads torch), starting from ``initial_weights``."""
        from learners.networks.policies import seeded_network

        initial = self.initial_weights(behavior, spec)
        return seeded_network(spec, self.settings_for(behavior), self._key(behavior), initial)

    def __call__(self, behavior: str, spec: BehaviorSpec) -> NumpyActor | TorchActor:
        settings = self.settings_for(behavior)
        if acts_in_numpy(spec, settings):
            return NumpyActor(spec, settings, self.initial_weights(behavior, spec))
        from learners.networks.policies import (
            TorchActor,  # goal conditioning: this worker needs torch
        )

        return TorchActor(self.network(behavior, spec))


def network_settings(settings: TrainerSettings) -> NetworkSettings:
    """A behavior's network settings, as its trainer type trains them (SAC: ML-Agents'
    squashed policy), in the learner and in every worker alike."""
    return trainer(settings).network(settings.network_settings)


def policy_factory(config: RunConfig, seed: int = 0) -> PolicyFactory:
    """The factory workers and learner share: network settings of each configured behavior,
    initial weights from the run's seed."""
    return PolicyFactory(
        {name: network_settings(s) for name, s in config.behaviors.items()},
        network_settings(config.default),
        seed,
    )


actor_factory = PolicyFactory()  # default networks: what tests and `collect` use
