"""ML-Agents ``BehaviorSpec`` -> torchrl ``Composite`` specs of one step.

Everything downstream (networks, buffers, validation of emitted segments) is built from
these specs, never from hard-coded shapes.
"""

from __future__ import annotations

import torch
from mlagents_envs.base_env import BehaviorSpec
from torchrl.data import Binary, Composite, MultiCategorical, Unbounded

from rollout import keys


def observation_spec(spec: BehaviorSpec) -> Composite:
    return Composite(
        {o.name: Unbounded(o.shape, dtype=torch.float32) for o in spec.observation_specs}
    )


def action_spec(spec: BehaviorSpec) -> Composite:
    """Continuous part: the raw Gaussian sample (Unity clips to [-1, 1]); discrete: one
    index per branch."""
    parts = {}
    if spec.action_spec.continuous_size:
        size = spec.action_spec.continuous_size
        parts[keys.CONTINUOUS] = Unbounded((size,), dtype=torch.float32)
    if spec.action_spec.discrete_branches:
        parts[keys.DISCRETE] = MultiCategorical(
            nvec=list(spec.action_spec.discrete_branches), dtype=torch.int64
        )
    return Composite(parts)


def step_spec(spec: BehaviorSpec) -> Composite:
    """One step of a segment row: what the worker records per decision and its outcome."""
    scalar_float = Unbounded((1,), dtype=torch.float32)
    flag = Binary(1, shape=(1,), dtype=torch.bool)
    entries = {
        keys.OBS: observation_spec(spec),
        keys.ACTION: action_spec(spec),
        keys.LOG_PROB: Unbounded((), dtype=torch.float32),
        keys.POLICY_VERSION: Unbounded((), dtype=torch.int64),
        keys.AGENT_ID: Unbounded((), dtype=torch.int64),
        keys.GROUP_ID: Unbounded((), dtype=torch.int64),
        keys.VALID: Binary(shape=(), dtype=torch.bool),
        keys.NEXT: Composite(
            {
                keys.OBS: observation_spec(spec),
                keys.REWARD: scalar_float,
                keys.GROUP_REWARD: scalar_float.clone(),
                keys.DONE: flag,
                keys.TERMINATED: flag.clone(),
                keys.TRUNCATED: flag.clone(),
            }
        ),
    }
    if spec.action_spec.discrete_branches:
        size = sum(spec.action_spec.discrete_branches)
        entries[keys.ACTION_MASK] = Binary(size, shape=(size,), dtype=torch.bool)
    return Composite(entries)
