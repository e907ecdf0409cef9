"""Synthetic segments in the worker format (docs/batch-format.md): the test double of a
worker's output, for learner tests."""

from __future__ import annotations

from dataclasses import replace

import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec, DimensionProperty, ObservationSpec
from mlagents_envs.base_env import ObservationType as Obs
from tensordict import TensorDict

from batches import keys
from batches.specs import log_prob_size, spec_to_dict, step_spec
from learners.host.devices import Compute

# the devices a learner test can run on here: the CPU, and CUDA on a machine that has it
DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]
VECTOR = ObservationSpec((8,), (DimensionProperty.NONE,), Obs.DEFAULT, "vector")
GRID = ObservationSpec((2, 3), (DimensionProperty.NONE,) * 2, Obs.DEFAULT, "rank2")
BUFFER = ObservationSpec(  # a BufferSensor: up to 6 entities of 5 numbers, zero rows absent
    (6, 5), (DimensionProperty.VARIABLE_SIZE, DimensionProperty.NONE), Obs.DEFAULT, "buffer"
)
IMAGE = ObservationSpec(  # the default (simple) encoder's smallest image
    (3, 20, 20),
    (
        DimensionProperty.NONE,
        DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,
        DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,
    ),
    Obs.DEFAULT,
    "camera",
)


def vector_spec(size: int = 4, continuous: int = 0, branches: tuple[int, ...] = ()) -> BehaviorSpec:
    sensor = ObservationSpec((size,), (DimensionProperty.NONE,), Obs.DEFAULT, "vector")
    return BehaviorSpec([sensor], ActionSpec(continuous, branches))


def segment(
    spec: BehaviorSpec, rows: int, steps: int, behavior: str = "B?team=0", seed: int = 0
) -> TensorDict:
    """Random but well-formed packed segment of ``rows`` trajectories of ``steps`` steps
    each, every one cut at its last step (``truncated``, as at a horizon cut), no episode
    end, every action allowed. Within a trajectory a step's next observation is the next
    step's observation, as workers pack them."""
    torch.manual_seed(seed)
    n = rows * steps
    batch = step_spec(spec).expand(n).rand()
    cut = torch.zeros(n, 1, dtype=torch.bool)
    cut[steps - 1 :: steps] = True
    batch[keys.NEXT, keys.DONE] = cut
    batch[keys.NEXT, keys.TRUNCATED] = cut.clone()
    batch[keys.NEXT, keys.TERMINATED] = torch.zeros(n, 1, dtype=torch.bool)
    batch[keys.NEXT, keys.GROUP_REWARD] = torch.zeros(n, 1)  # no group
    within = ~cut[:-1, 0]
    for name, obs in batch[keys.OBS].items():
        batch[keys.NEXT, keys.OBS, name][:-1][within] = obs[1:][within]
    if spec.action_spec.discrete_branches:
        batch[keys.ACTION_MASK] = torch.ones_like(batch[keys.ACTION_MASK])
    batch[keys.POLICY_VERSION] = torch.zeros(n, dtype=torch.int64)
    batch[keys.LOG_PROB] = torch.full((n, log_prob_size(spec)), -1.0)
    batch.set_non_tensor(keys.BEHAVIOR, behavior)
    batch.set_non_tensor(keys.SPEC, spec_to_dict(spec))
    return batch


def compute_of(device: str, mixed_precision: bool) -> Compute:
    """``Compute.of``, with bfloat16 kept where the learner would fall back to float32 for
    speed (a CPU without bfloat16 instructions): its path is tested on every machine."""
    return replace(Compute.of(device), mixed_precision=mixed_precision)
