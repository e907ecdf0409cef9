"""Every unitysim environment, launched like a build and read through the real
``UnityEnvironment``, reproduces the reference dumps of the real example builds."""

from __future__ import annotations

import numpy as np
import pytest
from mlagents_envs.base_env import ObservationType

from tests.unitysim.reference import REFERENCE

pytestmark = pytest.mark.integration


def steps_summary(steps, with_mask: bool) -> dict:
    summary = {
        "agent_id": [int(a) for a in steps.agent_id],
        "group_id": [int(g) for g in steps.group_id],
        "observation_shapes": [o.shape for o in steps.obs],
    }
    if with_mask:
        mask = steps.action_mask
        summary["action_mask_shapes"] = None if mask is None else [m.shape for m in mask]
    return summary


@pytest.mark.parametrize("name", list(REFERENCE))
def test_specs_and_first_steps_match_reference(name, open_env):
    reference = REFERENCE[name]
    with open_env(name, seed=0) as env:
        env.reset()
        assert list(env.behavior_specs) == list(reference)
        for behavior_name, expected in reference.items():
            spec = env.behavior_specs[behavior_name]
            got_sensors = [
                (
                    o.name,
                    o.shape,
                    tuple(int(d) for d in o.dimension_property),
                    o.observation_type.name,
                )
                for o in spec.observation_specs
            ]
            want_sensors = [
                (s.name, s.shape, s.dimension_property, s.observation_type)
                for s in expected.sensors
            ]
            assert got_sensors == want_sensors, behavior_name
            assert spec.action_spec.continuous_size == expected.continuous
            assert spec.action_spec.discrete_branches == expected.branches

            decisions, terminals = env.get_steps(behavior_name)
            assert steps_summary(decisions, with_mask=True) == {
                "agent_id": expected.decision.agent_id,
                "group_id": expected.decision.group_id,
                "observation_shapes": expected.decision.observation_shapes,
                "action_mask_shapes": expected.decision.action_mask_shapes,
            }, behavior_name
            assert steps_summary(terminals, with_mask=False) == {
                "agent_id": expected.terminal.agent_id,
                "group_id": expected.terminal.group_id,
                "observation_shapes": expected.terminal.observation_shapes,
            }, behavior_name
            for obs in decisions.obs:
                assert np.isfinite(obs).all()


def test_basic_matches_the_example(open_env):
    with open_env("Basic", seed=0) as env:
        env.reset()
        assert list(env.behavior_specs) == ["Basic?team=0"]
        spec = env.behavior_specs["Basic?team=0"]
        assert [(o.name, o.shape) for o in spec.observation_specs] == [("Basic", (20,))]
        assert spec.action_spec.discrete_branches == (3,)
        decisions, _ = env.get_steps("Basic?team=0")
        assert len(decisions) == 1
        np.testing.assert_array_equal(decisions.obs[0][0], np.eye(20, dtype=np.float32)[10])


def test_gridworld_matches_the_example(open_env):
    with open_env("GridWorld", seed=0) as env:
        env.reset()
        spec = env.behavior_specs["GridWorld?team=0"]
        visual, goal = spec.observation_specs
        assert len(visual.shape) == 3 and visual.shape[0] == 3
        assert goal.shape == (2,) and goal.observation_type == ObservationType.GOAL_SIGNAL
        assert spec.action_spec.discrete_branches == (5,)
        decisions, _ = env.get_steps("GridWorld?team=0")
        assert len(decisions) == 9
        image = decisions.obs[0]
        assert image.shape == (9, *visual.shape) and image.min() >= 0.0 and image.max() <= 1.0
        assert decisions.action_mask[0].shape == (9, 5)
        assert decisions.action_mask[0].any(), "moves into walls are masked"
