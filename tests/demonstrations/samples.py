"""Demonstrations to write and read: vector, hybrid and image sensors, several episodes."""

from __future__ import annotations

import numpy as np
from mlagents_envs.base_env import (
    ActionSpec,
    BehaviorSpec,
    DimensionProperty,
    ObservationSpec,
    ObservationType,
)

from demonstrations import Demonstration, DemoStep

NONE, SPATIAL = DimensionProperty.NONE, DimensionProperty.TRANSLATIONAL_EQUIVARIANCE


def sensor(shape, name, dims=None, kind=ObservationType.DEFAULT) -> ObservationSpec:
    dims = dims or ((NONE,) if len(shape) == 1 else (NONE, SPATIAL, SPATIAL)[: len(shape)])
    return ObservationSpec(shape=shape, dimension_property=dims, observation_type=kind, name=name)


def spec(sensors, continuous=0, branches=()) -> BehaviorSpec:
    return BehaviorSpec(list(sensors), ActionSpec(continuous, tuple(branches)))


def steps(behavior: BehaviorSpec, count: int, seed: int = 0, pixels: bool = False):
    """``count`` steps, an episode ending every 5 (every second one cut by its step limit);
    ``pixels``: 3-D observations are multiples of 1/255 (exact through PNG)."""
    rng = np.random.default_rng(seed)
    actions = behavior.action_spec
    out = []
    for i in range(count):
        observations = tuple(
            rng.integers(0, 256, o.shape).astype(np.float32) / np.float32(255)
            if pixels and len(o.shape) == 3
            else rng.normal(size=o.shape).astype(np.float32)
            for o in behavior.observation_specs
        )
        done = i % 5 == 4
        out.append(
            DemoStep(
                observations=observations,
                reward=float(np.float32(rng.normal())),
                done=done,
                interrupted=done and i % 10 == 9,
                agent_id=7 + i // 5,
                action_mask=rng.random(sum(actions.discrete_branches)) < 0.3,
                continuous=rng.normal(size=actions.continuous_size),
                discrete=[rng.integers(0, b) for b in actions.discrete_branches],
                group_id=i // 5 % 2,
                group_reward=float(np.float32(rng.normal())),
            )
        )
    return out


def demonstration(behavior: BehaviorSpec, count: int = 12, **kwargs) -> Demonstration:
    return Demonstration.of_steps(
        "Expert", "Walker?team=0", behavior, steps(behavior, count, **kwargs)
    )


DISCRETE = spec([sensor((8,), "VectorSensor_size8"), sensor((3,), "Ray")], branches=(3, 2))
CONTINUOUS = spec([sensor((6,), "VectorSensor_size6")], continuous=2)
HYBRID = spec(
    [
        sensor((5,), "VectorSensor_size5", kind=ObservationType.GOAL_SIGNAL),
        sensor((4, 3), "Buffer", dims=(DimensionProperty.VARIABLE_SIZE, NONE)),
        sensor((2, 4, 4), "Grid"),
    ],
    continuous=3,
    branches=(4,),
)
IMAGES = spec(
    [sensor((3, 8, 8), "Camera"), sensor((1, 5, 5), "Grey"), sensor((5, 4, 4), "Grid")],
    branches=(2,),
)
