"""A user's policy, a ``TensorDictModule``, acting in every worker (``batches.contracts.Actor``).

The module reads ``observation`` (a tensor, or a TensorDict of sensors by name when the
behavior has several) and ``action_mask`` (discrete behaviors: True = allowed), and writes
``action`` (continuous ``[n, c]`` float, discrete ``[n, branches]`` integer, or both under
``continuous`` and ``discrete`` for a hybrid action) and, if it samples,
``action_log_prob`` (``[n]``; or ``sample_log_prob``, its older name): the names of
``torchrl_adapters.conventions``, which the batches come back under. Unity gets the
continuous action as the module wrote it.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from mlagents_envs.base_env import BehaviorSpec
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from batches import keys
from batches.contracts import base_name
from torchrl_adapters.conventions import ACTION, LEGACY_LOG_PROB, LOG_PROB, OBSERVATION, observation


class ModuleActor:
    def __init__(self, module: TensorDictModuleBase, spec: BehaviorSpec) -> None:
        self.module = module
        self.sensors = [o.name for o in spec.observation_specs]
        self.continuous = spec.action_spec.continuous_size
        self.branches = len(spec.action_spec.discrete_branches)

    def act(
        self, obs: dict[str, np.ndarray], mask: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(next(iter(obs.values())))
        sensors = TensorDict({k: torch.from_numpy(obs[k]) for k in self.sensors}, batch_size=[n])
        given = TensorDict({OBSERVATION: observation(sensors)}, batch_size=[n])
        if mask is not None:
            given[keys.ACTION_MASK] = torch.from_numpy(mask)
        with torch.no_grad():
            out = self.module(given)
        action = out[ACTION]
        if self.continuous and self.branches:
            continuous, discrete = action[keys.CONTINUOUS], action[keys.DISCRETE]
        elif self.continuous:
            continuous, discrete = action, torch.zeros(n, 0, dtype=torch.int64)
        else:
            continuous, discrete = torch.zeros(n, 0), action
        # one log-probability per component in our segments; the action's (their sum)
        # is what torchrl's losses read, so the module's total goes to the first
        log_prob = np.zeros((n, self.continuous + self.branches), np.float32)
        written = next((k for k in (LOG_PROB, LEGACY_LOG_PROB) if k in out), None)
        if written is not None and log_prob.shape[1]:
            log_prob[:, 0] = out[written].reshape(n).float().numpy()
        return (
            continuous.reshape(n, self.continuous).float().numpy(),
            discrete.reshape(n, self.branches).long().numpy(),
            log_prob,
        )

    def to_unity(self, continuous: np.ndarray) -> np.ndarray:
        return continuous

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.module.load_state_dict({k: torch.as_tensor(v) for k, v in state.items()})


@dataclass(frozen=True)
class ModuleActorFactory:
    """Pickled to every worker: each behavior acts with its own copy of ``policy`` (one
    module for all behaviors, or one per behavior name without ``?team=``)."""

    policy: TensorDictModuleBase | Mapping[str, TensorDictModuleBase]

    def module(self, behavior: str) -> TensorDictModuleBase:
        if isinstance(self.policy, Mapping):
            if base_name(behavior) not in self.policy:
                raise KeyError(
                    f"behavior {base_name(behavior)}: no policy given for it "
                    f"(the policies are for {', '.join(sorted(self.policy))})"
                )
            return self.policy[base_name(behavior)]
        return self.policy

    def __call__(self, behavior: str, spec: BehaviorSpec) -> ModuleActor:
        return ModuleActor(copy.deepcopy(self.module(behavior)).cpu(), spec)
