"""Visual3DBall's stand-in: 3DBall seen through the example's stacked camera, its frames
sent as PNGs with the StackingSensor's compressed channel mapping, decoded by the real client."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from mlagents_envs.base_env import ActionTuple
from mlagents_envs.communicator_objects.agent_info_pb2 import AgentInfoProto
from mlagents_envs.rpc_utils import process_pixels

from tests.unitysim.test_learnable_envs import make
from unitysim import png
from unitysim.envs.ball3d import Visual3DBall
from unitysim.envs.base import AgentInfos, Behavior, Sensor
from unitysim.messages import agent_infos

BEHAVIOR = "Visual3DBall?team=0"
# a grid sensor of five channels stacked over two frames: two PNGs a frame
STACKED_GRID = replace(Sensor.visual("StackingSensor_size2_GridSensor", 10, 6, 7), stacks=2)


def test_a_stacks_mapping_pads_each_frame_to_whole_pngs_as_unitys_stacking_sensor():
    five = STACKED_GRID
    assert five.channel_mapping == (0, 1, 2, 3, 4, -1, 5, 6, 7, 8, 9, -1)
    assert Visual3DBall.behaviors[0].sensors[0].channel_mapping == tuple(range(12))
    assert Sensor.visual("GridSensor", 5, 6, 7).channel_mapping == ()  # nothing stacked


def test_the_real_decoder_reads_a_stack_of_five_channel_frames_back_with_its_mapping():
    sensor = STACKED_GRID
    rng = np.random.default_rng(0)
    frames = (rng.integers(0, 256, (10, 6, 7)) / 255.0).astype(np.float32)
    (proto,) = [o for info in _infos(sensor, frames) for o in info.observations]
    assert list(proto.compressed_channel_mapping) == list(sensor.channel_mapping)
    assert proto.compressed_data.count(b"\x89PNG") == 4  # two PNGs a frame
    decoded = process_pixels(proto.compressed_data, 10, list(proto.compressed_channel_mapping))
    np.testing.assert_allclose(decoded, frames, atol=1e-6)
    # without the mapping a decoder would take the padding channel for the second frame's first
    assert not np.allclose(process_pixels(proto.compressed_data, 10, None), frames)


def _infos(sensor: Sensor, frames: np.ndarray) -> list[AgentInfoProto]:
    behavior = Behavior("Stacked?team=0", (sensor,), continuous=1)
    return agent_infos(behavior, AgentInfos.build(np.array([0]), [frames[None]]))


def test_the_real_client_sees_the_stacked_camera_and_the_stack_moves_on_by_a_frame(open_env):
    with open_env("Visual3DBall") as env:
        env.reset()
        spec = env.behavior_specs[BEHAVIOR]
        (camera,) = spec.observation_specs
        assert camera.name == "StackingSensor_size4_CameraSensor"
        assert camera.shape == (12, 84, 84)
        assert spec.action_spec.continuous_size == 2 and spec.action_spec.discrete_size == 0
        first, _ = env.get_steps(BEHAVIOR)
        assert len(first) == 8
        stack = first.obs[0]
        assert not stack[:, :9].any()  # an episode's start: the older frames are zeros
        assert (stack[:, 9:].reshape(8, -1).max(1) > 0.2).all()  # the platform, the ball
        env.set_actions(BEHAVIOR, ActionTuple(continuous=np.zeros((8, 2), np.float32)))
        env.step()
        second, _ = env.get_steps(BEHAVIOR)
        np.testing.assert_array_equal(second.obs[0][:, 6:9], stack[:, 9:])


def test_the_picture_follows_the_ball_and_the_tilt():
    env = make("Visual3DBall", seed=4)
    assert isinstance(env, Visual3DBall)
    env.reset()
    env.xz[:] = 0.0
    env.sigma[:] = 0.0
    env.y[:] = env.radius  # resting at the centre, the platform flat
    centred = env._observe()[:, 9:]
    env.xz[0, :] = 2.0  # the balls at the right edge
    right = env._observe()[:, 9:]
    ball = np.all(np.isclose(centred[0].transpose(1, 2, 0), [0.93, 0.62, 0.27], atol=0.01), -1)
    moved = np.all(np.isclose(right[0].transpose(1, 2, 0), [0.93, 0.62, 0.27], atol=0.01), -1)
    assert ball.any() and moved.any()
    assert np.nonzero(moved)[1].mean() > np.nonzero(ball)[1].mean() + 10  # to the image's right
    env.sigma[1, :] = 0.3  # tilted about x: the top face turns from the light
    assert env._observe()[:, 9:].max() <= right.max()
    assert png.encode(centred[0])[:8] == b"\x89PNG\r\n\x1a\n"
