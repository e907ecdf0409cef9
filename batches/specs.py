"""ML-Agents ``BehaviorSpec`` -> torchrl ``Composite`` specs of one step, and the spec as
plain data (what travels with each segment).

Everything downstream (networks, buffers, validation of emitted segments) is built from
these specs, never from hard-coded shapes. torch and torchrl are imported by the functions
that build torchrl specs (the learner's side and tests), so workers never load them.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from mlagents_envs.base_env import (
    ActionSpec,
    BehaviorSpec,
    DimensionProperty,
    ObservationSpec,
    ObservationType,
)

from batches import keys

if TYPE_CHECKING:
    from torchrl.data import Composite


def observation_spec(spec: BehaviorSpec, pixel_sensors: Iterable[str] = ()) -> Composite:
    """float32 per sensor; ``pixel_sensors`` (sent by Unity as PNG) as uint8 0..255."""
    import torch
    from torchrl.data import Bounded, Composite, Unbounded

    pixels = set(pixel_sensors)
    return Composite(
        {
            o.name: Bounded(0, 255, o.shape, dtype=torch.uint8)
            if o.name in pixels
            else Unbounded(o.shape, dtype=torch.float32)
            for o in spec.observation_specs
        }
    )


def action_spec(spec: BehaviorSpec) -> Composite:
    """Continuous part: the raw Gaussian sample; discrete: one index per branch."""
    import torch
    from torchrl.data import Composite, MultiCategorical, Unbounded

    parts = {}
    if spec.action_spec.continuous_size:
        size = spec.action_spec.continuous_size
        parts[keys.CONTINUOUS] = Unbounded((size,), dtype=torch.float32)
    if spec.action_spec.discrete_branches:
        parts[keys.DISCRETE] = MultiCategorical(
            nvec=list(spec.action_spec.discrete_branches), dtype=torch.int64
        )
    return Composite(parts)


def log_prob_size(spec: BehaviorSpec) -> int:
    """Log-probabilities per step: one per continuous dimension and per discrete branch,
    as ML-Agents keeps them (its PPO clips each component's ratio)."""
    return spec.action_spec.continuous_size + len(spec.action_spec.discrete_branches)


def step_spec(spec: BehaviorSpec, pixel_sensors: Iterable[str] = ()) -> Composite:
    """One step of a segment: what the worker records per decision and its outcome."""
    import torch
    from torchrl.data import Binary, Composite, Unbounded

    scalar_float = Unbounded((1,), dtype=torch.float32)
    flag = Binary(1, shape=(1,), dtype=torch.bool)
    entries = {
        keys.OBS: observation_spec(spec, pixel_sensors),
        keys.ACTION: action_spec(spec),
        keys.LOG_PROB: Unbounded((log_prob_size(spec),), dtype=torch.float32),
        keys.POLICY_VERSION: Unbounded((), dtype=torch.int64),
        keys.AGENT_ID: Unbounded((), dtype=torch.int64),
        keys.GROUP_ID: Unbounded((), dtype=torch.int64),
        keys.NEXT: Composite(
            {
                keys.OBS: observation_spec(spec, pixel_sensors),
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


def spec_to_dict(spec: BehaviorSpec) -> dict[str, Any]:
    return {
        "observations": [
            {
                "name": o.name,
                "shape": list(o.shape),
                "dimension_property": [int(p.value) for p in o.dimension_property],
                "observation_type": o.observation_type.value,
            }
            for o in spec.observation_specs
        ],
        "continuous": int(spec.action_spec.continuous_size),
        "discrete": [int(b) for b in spec.action_spec.discrete_branches],
    }


def spec_from_dict(data: dict[str, Any]) -> BehaviorSpec:
    observations = [
        ObservationSpec(
            tuple(o["shape"]),
            tuple(DimensionProperty(p) for p in o["dimension_property"]),
            ObservationType(o["observation_type"]),
            o["name"],
        )
        for o in data["observations"]
    ]
    return BehaviorSpec(observations, ActionSpec(data["continuous"], tuple(data["discrete"])))


def spec_mismatch(found: BehaviorSpec, expected: BehaviorSpec) -> str | None:
    """What differs in actions or sensor shapes (all ML-Agents compares), or None."""
    if found.action_spec != expected.action_spec:
        return f"actions {_actions(found)} do not match the expected {_actions(expected)}"
    shapes = [o.shape for o in found.observation_specs]
    wanted = [o.shape for o in expected.observation_specs]
    if shapes != wanted:
        return f"observation shapes {shapes} do not match the expected {wanted}"
    return None


def _actions(spec: BehaviorSpec) -> str:
    a = spec.action_spec
    return f"(continuous {a.continuous_size}, discrete branches {list(a.discrete_branches)})"
