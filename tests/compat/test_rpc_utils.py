"""mlagents_envs.rpc_utils turns hand-built protos into DecisionSteps/TerminalSteps
correctly under numpy 2 and current Pillow."""

import io

import numpy as np
import pytest
from mlagents_envs.base_env import ActionSpec, DimensionProperty, ObservationType
from mlagents_envs.communicator_objects.agent_info_pb2 import AgentInfoProto
from mlagents_envs.communicator_objects.brain_parameters_pb2 import (
    ActionSpecProto,
    BrainParametersProto,
)
from mlagents_envs.communicator_objects.observation_pb2 import (
    GOAL_SIGNAL,
    NONE,
    PNG,
    ObservationProto,
)
from mlagents_envs.rpc_utils import behavior_spec_from_proto, steps_from_proto
from PIL import Image


def float_obs(values, shape, name="VectorSensor"):
    return ObservationProto(
        shape=shape,
        compression_type=NONE,
        float_data=ObservationProto.FloatData(data=list(np.ravel(values))),
        dimension_properties=[1] * len(shape),
        name=name,
    )


def png_bytes(hwc_uint8: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(hwc_uint8, mode="RGB").save(buffer, format="PNG")
    return buffer.getvalue()


def png_obs(chw_uint8: np.ndarray, name="CameraSensor", observation_type=0):
    """Encode C channels as ceil(C/3) concatenated RGB PNGs, as Unity does."""
    channels, height, width = chw_uint8.shape
    padded = np.zeros((-(-channels // 3) * 3, height, width), dtype=np.uint8)
    padded[:channels] = chw_uint8
    data = b"".join(
        png_bytes(np.moveaxis(padded[i : i + 3], 0, -1)) for i in range(0, len(padded), 3)
    )
    return ObservationProto(
        shape=[channels, height, width],
        compression_type=PNG,
        compressed_data=data,
        dimension_properties=[1, 2, 2],
        observation_type=observation_type,
        name=name,
    )


def brain(name, continuous=0, branches=()):
    return BrainParametersProto(
        brain_name=name,
        is_training=True,
        action_spec=ActionSpecProto(
            num_continuous_actions=continuous,
            num_discrete_actions=len(branches),
            discrete_branch_sizes=list(branches),
        ),
    )


def test_float_observations_and_spec():
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(3, 8)).astype(np.float32)
    grid = rng.normal(size=(3, 2, 5)).astype(np.float32)
    infos = [
        AgentInfoProto(
            id=i,
            reward=0.1 * i,
            observations=[float_obs(obs[i], [8]), float_obs(grid[i], [2, 5], "Rank2")],
            group_id=i % 2,
            group_reward=-0.5 * i,
        )
        for i in range(3)
    ]
    spec = behavior_spec_from_proto(brain("3DBall?team=0", continuous=2), infos[0])
    assert spec.action_spec == ActionSpec(2, ())
    assert [o.shape for o in spec.observation_specs] == [(8,), (2, 5)]
    assert spec.observation_specs[0].name == "VectorSensor"
    assert spec.observation_specs[1].dimension_property == (DimensionProperty.NONE,) * 2

    decisions, terminals = steps_from_proto(infos, spec)
    assert len(decisions) == 3 and len(terminals) == 0
    np.testing.assert_array_equal(decisions.obs[0], obs)
    np.testing.assert_array_equal(decisions.obs[1], grid)  # rank 2 rows are row-major
    assert decisions.obs[0].dtype == np.float32
    np.testing.assert_allclose(decisions.reward, [0.0, 0.1, 0.2], rtol=1e-6)
    np.testing.assert_array_equal(decisions.agent_id, [0, 1, 2])
    np.testing.assert_array_equal(decisions.group_id, [0, 1, 0])
    np.testing.assert_allclose(decisions.group_reward, [0.0, -0.5, -1.0])
    assert decisions.action_mask is None
    assert terminals.obs[0].shape == (0, 8)


def test_single_png_observation_and_goal_signal():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, size=(2, 3, 6, 5), dtype=np.uint8)
    infos = [
        AgentInfoProto(
            id=10 + i,
            observations=[
                png_obs(image[i]),
                float_obs([0.0, 1.0], [2], "GoalSignal"),
            ],
        )
        for i in range(2)
    ]
    infos[0].observations[1].observation_type = GOAL_SIGNAL
    infos[1].observations[1].observation_type = GOAL_SIGNAL
    spec = behavior_spec_from_proto(brain("GridWorld?team=0", branches=(5,)), infos[0])
    assert spec.observation_specs[0].shape == (3, 6, 5)
    assert spec.observation_specs[1].observation_type == ObservationType.GOAL_SIGNAL
    assert spec.observation_specs[0].dimension_property == (
        DimensionProperty.NONE,
        DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,
        DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,
    )
    decisions, _ = steps_from_proto(infos, spec)
    np.testing.assert_allclose(decisions.obs[0], image.astype(np.float32) / 255.0, atol=1e-6)


def test_concatenated_pngs_for_more_than_three_channels():
    rng = np.random.default_rng(2)
    image = rng.integers(0, 256, size=(5, 4, 4), dtype=np.uint8)
    info = AgentInfoProto(id=0, observations=[png_obs(image, "GridSensor")])
    spec = behavior_spec_from_proto(brain("Grid?team=0", branches=(2,)), info)
    decisions, _ = steps_from_proto([info], spec)
    assert decisions.obs[0].shape == (1, 5, 4, 4)
    np.testing.assert_allclose(decisions.obs[0][0], image / 255.0, atol=1e-6)


def test_one_channel_png_is_grey_average():
    rgb = np.array([[[30, 60, 90], [0, 0, 3]]], dtype=np.uint8)  # H=1, W=2, RGB
    obs = ObservationProto(
        shape=[1, 1, 2], compression_type=PNG, compressed_data=png_bytes(rgb), name="Grey"
    )
    info = AgentInfoProto(id=0, observations=[obs])
    spec = behavior_spec_from_proto(brain("Grey?team=0", continuous=1), info)
    decisions, _ = steps_from_proto([info], spec)
    np.testing.assert_allclose(decisions.obs[0], [[[[60 / 255, 1 / 255]]]], atol=1e-6)


def test_action_masks_split_per_branch():
    obs = [float_obs([0.0], [1])]
    infos = [
        AgentInfoProto(id=0, observations=obs, action_mask=[False, True, False, False, False]),
        AgentInfoProto(id=1, observations=obs, action_mask=[]),  # empty: all allowed
        AgentInfoProto(id=2, observations=obs, action_mask=[True, True]),  # wrong length
        AgentInfoProto(id=3, observations=obs, done=True, action_mask=[True] * 5),
    ]
    spec = behavior_spec_from_proto(brain("Masked?team=0", branches=(3, 2)), infos[0])
    decisions, terminals = steps_from_proto(infos, spec)
    assert len(decisions) == 3 and len(terminals) == 1
    branch0, branch1 = decisions.action_mask
    np.testing.assert_array_equal(branch0, [[False, True, False], [False] * 3, [False] * 3])
    np.testing.assert_array_equal(branch1, [[False, False]] * 3)
    assert branch0.dtype == np.bool_


def test_terminal_and_decision_for_same_agent_in_one_step():
    infos = [
        AgentInfoProto(
            id=4,
            reward=-1.0,
            done=True,
            max_step_reached=True,
            observations=[float_obs([9.0, 9.0], [2])],
        ),
        AgentInfoProto(id=4, reward=0.0, observations=[float_obs([1.0, 2.0], [2])]),
        AgentInfoProto(id=5, reward=0.5, done=True, observations=[float_obs([3.0, 3.0], [2])]),
    ]
    spec = behavior_spec_from_proto(brain("Both?team=0", continuous=1), infos[1])
    decisions, terminals = steps_from_proto(infos, spec)
    np.testing.assert_array_equal(decisions.agent_id, [4])
    np.testing.assert_array_equal(decisions.obs[0], [[1.0, 2.0]])
    np.testing.assert_array_equal(terminals.agent_id, [4, 5])
    np.testing.assert_array_equal(terminals.obs[0], [[9.0, 9.0], [3.0, 3.0]])
    np.testing.assert_array_equal(terminals.interrupted, [True, False])
    np.testing.assert_allclose(terminals.reward, [-1.0, 0.5])
    assert terminals[4].interrupted and not terminals[5].interrupted
    assert decisions.agent_id_to_index[4] == 0


def test_nan_observation_is_rejected():
    info = AgentInfoProto(id=0, observations=[float_obs([np.nan, 1.0], [2])])
    spec = behavior_spec_from_proto(brain("Nan?team=0", continuous=1), info)
    with pytest.raises(RuntimeError, match="NaN"):
        steps_from_proto([info], spec)
