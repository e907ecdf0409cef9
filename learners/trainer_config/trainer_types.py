"""The trainer types, one entry each: everything the config, the learner, the acting
policy and the driver need to know of a ``trainer_type``. A new trainer is one more entry
here and its algorithm module.

Torch-free: the config and the driver read it; the learner imports ``algorithm`` lazily.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from learners.trainer_config.keys import (
    ON_POLICY,
    POSITIVE,
    SHARED,
    Check,
    float_in,
    int_from,
    optional,
)
from learners.trainer_config.settings import Hyperparameters, NetworkSettings, TrainerSettings


@dataclass(frozen=True)
class TrainerType:
    name: str
    algorithm: (
        str  # "module:Class" of the algorithm (learners/algorithms/ppo.py ...), loaded lazily
    )
    hyperparameters: Mapping[str, Check]  # the keys its config takes, each with its check
    # ML-Agents keys it has that we do not implement, each with the value that asks for what
    # we do anyway (not reported; ALWAYS: reported whatever the value)
    unsupported: Mapping[str, object] = field(default_factory=dict)
    defaults: Hyperparameters = field(default_factory=Hyperparameters)
    # on-policy: its next update wants ``buffer_size`` fresh steps, so the service holds
    # workers to that demand (learners.host.counters.on_policy_wanted)
    waits_for_fresh_data: bool = False
    # trains on whatever arrives, importance-corrected: workers keep two collects in flight
    asynchronous: bool = False
    # ML-Agents' SAC policy: tanh-squashed actions, log-std from a head on the trunk
    squashed: bool = False
    # "module:Class" of its algorithm with ``network_settings.memory``; None: the trainer
    # has no memory (the config reports the key unsupported)
    recurrent: str | None = None
    # it takes curiosity, rnd and gail (else the config reports them unsupported)
    signals: bool = False

    def settings(self) -> TrainerSettings:
        """ML-Agents' defaults for this trainer type."""
        return TrainerSettings(trainer_type=self.name, hyperparameters=self.defaults)

    def network(self, settings: NetworkSettings) -> NetworkSettings:
        """The network it trains, in the learner and in every worker alike."""
        if self.squashed:
            return replace(settings, tanh_squash=True, conditional_sigma=True)
        return settings

    def algorithm_class(self, memory: bool = False) -> Any:
        """Its algorithm; with ``memory``, the recurrent one."""
        path = self.recurrent if memory else self.algorithm
        assert path is not None, f"{self.name} has no memory"
        module, name = path.split(":")
        return getattr(importlib.import_module(module), name)


TRAINERS: Mapping[str, TrainerType] = {
    t.name: t
    for t in (
        TrainerType(
            "ppo",
            "learners.algorithms.ppo:PPO",
            {**SHARED, **ON_POLICY, "max_policy_lag": optional(int_from(0))},
            {"shared_critic": False},
            waits_for_fresh_data=True,
            recurrent="learners.algorithms.recurrent_ppo:RecurrentPPO",
            signals=True,
        ),
        TrainerType(
            "sac",
            "learners.algorithms.sac:SAC",
            {
                **SHARED,
                "buffer_init_steps": int_from(0),
                "tau": float_in(0, 1, open_low=True),
                "steps_per_update": POSITIVE,
                "init_entcoef": POSITIVE,
                # how often the networks of curiosity, rnd and gail update
                "reward_signal_steps_per_update": POSITIVE,
            },
            {"save_replay_buffer": False},
            Hyperparameters(batch_size=128, buffer_size=50_000, learning_rate_schedule="constant"),
            squashed=True,
            recurrent="learners.algorithms.recurrent_sac:RecurrentSAC",
            signals=True,
        ),
        TrainerType(  # PPO with a centralized critic over each group (learners/algorithms/poca.py)
            "poca",
            "learners.algorithms.poca:POCA",
            {**SHARED, **ON_POLICY, "max_policy_lag": optional(int_from(0))},
            waits_for_fresh_data=True,
        ),
        TrainerType(  # not in ML-Agents: PPO's defaults, one epoch
            "impala",
            "learners.algorithms.impala:IMPALA",
            {**SHARED, **ON_POLICY, "vtrace_rho_clip": POSITIVE, "vtrace_c_clip": POSITIVE},
            {"shared_critic": False},
            Hyperparameters(num_epoch=1),
            asynchronous=True,
        ),
    )
}


def trainer(settings: TrainerSettings) -> TrainerType:
    return TRAINERS[settings.trainer_type]
