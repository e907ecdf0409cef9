"""Files laid out as Unity's C# recorder writes them (``unity_style``), read by our reader;
and our writer producing the very same bytes."""

import numpy as np
import pytest
from mlagents_envs.base_env import ActionSpec, DimensionProperty, ObservationType

from demonstrations import DemoMeta, read_demo, write_demo
from tests.demonstrations import samples
from tests.demonstrations.unity_style import (
    UnityStyleWriter,
    brain,
    pair,
    png_obs,
    vector_obs,
)


def pushbutton_like(close: bool = True) -> tuple[bytes, list]:
    """4 floats, discrete branches (3, 3, 2), 7 steps in two episodes (as a real
    PushButton recording made with com.unity.ml-agents 2.0.1 is laid out)."""
    writer = UnityStyleWriter("PushButtonAgentD", brain("PushButton?team=0", branches=(3, 3, 2)))
    rng = np.random.default_rng(3)
    records = []
    for i in range(7):
        record = pair(
            [vector_obs(rng.normal(size=4))],
            reward=1.0 if i in (3, 6) else -0.01,
            done=i in (3, 6),
            agent_id=12,
            mask=[False, True, False, False, False, False, False, True],
            discrete=[i % 3, 1, i % 2],
        )
        records.append(record)
        writer.record(record)
    return (writer.close() if close else writer.unclosed()), records


def test_the_layout_is_the_one_unity_writes():
    data, records = pushbutton_like()
    meta_size = data[0]
    assert 1 + meta_size <= 33 and set(data[1 + meta_size : 33]) == {0}  # zero padding
    brain_size = data[33]
    end = 34 + brain_size
    for record in records:
        body = record.SerializeToString()
        assert data[end] == len(body) and data[end + 1 : end + 1 + len(body)] == body
        end += 1 + len(body)
    assert data[end:] == data[1 : 1 + meta_size]  # the undelimited copy at the end


def test_our_reader_reads_a_unity_style_file(tmp_path):
    data, records = pushbutton_like()
    (tmp_path / "push.demo").write_bytes(data)
    demo = read_demo(tmp_path / "push.demo")
    assert demo.meta.name == "PushButtonAgentD"
    assert (demo.meta.steps, demo.meta.episodes) == (7, 3)  # Unity's Close counts one more
    assert demo.meta.mean_reward == pytest.approx((2.0 - 0.05) / 3, rel=1e-6)
    assert demo.behavior_name == "PushButton?team=0"
    assert demo.behavior_spec.action_spec == ActionSpec(0, (3, 3, 2))
    [sensor] = demo.behavior_spec.observation_specs
    assert sensor.shape == (4,) and sensor.name == "VectorSensor_size4"
    assert sensor.dimension_property == (DimensionProperty.NONE,)
    assert sensor.observation_type == ObservationType.DEFAULT
    for step, record in zip(demo.steps, records, strict=True):
        info = record.agent_info
        np.testing.assert_array_equal(
            step.observations[0], np.float32(info.observations[0].float_data.data)
        )
        assert step.reward == np.float32(info.reward)
        assert (step.done, step.agent_id) == (info.done, 12)
        assert step.action_mask.tolist() == list(info.action_mask)
        assert step.discrete.tolist() == list(record.action_info.discrete_actions)


def test_our_writer_writes_unitys_bytes(tmp_path):
    data, _ = pushbutton_like()
    (tmp_path / "push.demo").write_bytes(data)
    demo = read_demo(tmp_path / "push.demo")
    write_demo(tmp_path / "again.demo", demo)
    assert (tmp_path / "again.demo").read_bytes() == data


def test_our_writer_writes_unitys_bytes_for_continuous_and_hybrid_actions(tmp_path):
    for behavior, kind in ((samples.CONTINUOUS, "continuous"), (samples.HYBRID, "hybrid")):
        demo = samples.demonstration(behavior, count=6)
        actions = behavior.action_spec
        writer = UnityStyleWriter(
            "Expert", brain("Walker?team=0", actions.continuous_size, actions.discrete_branches)
        )
        for step in demo.steps:
            record = pair(
                [],
                reward=step.reward,
                done=step.done,
                max_step=step.interrupted,
                agent_id=step.agent_id,
                mask=step.action_mask.tolist(),
                continuous=step.continuous.tolist(),
                discrete=step.discrete.tolist(),
            )
            record.agent_info.group_id = step.group_id
            record.agent_info.group_reward = step.group_reward
            for obs, sensor in zip(step.observations, behavior.observation_specs, strict=True):
                proto = vector_obs(obs, sensor.name)
                proto.dimension_properties[:] = [int(d) for d in sensor.dimension_property]
                proto.observation_type = sensor.observation_type.value
                record.agent_info.observations.append(proto)
            writer.record(record)
        data = writer.close()
        meta = read_demo(_saved(tmp_path, kind, data)).meta
        write_demo(tmp_path / "ours.demo", _with_meta(demo, meta))
        assert (tmp_path / "ours.demo").read_bytes() == data, kind


def test_a_recording_unity_never_closed_is_read_to_its_end(tmp_path):
    data, records = pushbutton_like(close=False)
    demo = read_demo(_saved(tmp_path, "cut", data))
    assert demo.meta == DemoMeta("PushButtonAgentD", len(records), 0, 0.0)
    assert len(demo.steps) == 7


def test_files_from_before_the_action_spec(tmp_path):
    """API version 0 era: brain parameters with only the deprecated fields, actions in
    ``vector_actions_deprecated`` (continuous when the spec is continuous, else discrete)."""
    for continuous, branches, actions in ((2, (), [0.5, -1.0]), (0, (3, 4), [2.0, 3.0])):
        writer = UnityStyleWriter("Old", brain("Old", continuous, branches, True), api_version=0)
        writer.record(pair([vector_obs([1.0, 2.0])], deprecated=actions))
        writer.record(pair([vector_obs([3.0, 4.0])], done=True, deprecated=actions))
        demo = read_demo(_saved(tmp_path, "old", writer.close()))
        assert demo.behavior_spec.action_spec == ActionSpec(continuous, branches)
        step = demo.steps[0]
        assert step.continuous.tolist() == (actions if continuous else [])
        assert step.discrete.tolist() == ([] if continuous else [2, 3])


def test_png_camera_and_grid_sensors(tmp_path):
    rng = np.random.default_rng(5)
    camera = rng.integers(0, 256, (3, 6, 7), dtype=np.uint8)
    grey = rng.integers(0, 256, (1, 4, 4), dtype=np.uint8)
    grid = rng.integers(0, 256, (5, 3, 3), dtype=np.uint8)
    writer = UnityStyleWriter("Eyes", brain("Eyes?team=0", branches=(2,)))
    greyscale = png_obs(np.repeat(grey, 3, axis=0), "Grey")  # Unity's: R = G = B
    greyscale.shape[:] = [1, 4, 4]  # one channel in the shape
    observations = [png_obs(camera), greyscale, png_obs(grid, "Grid", [0, 1, 2, 3, 4, -1])]
    writer.record(pair(observations, discrete=[1]))
    demo = read_demo(_saved(tmp_path, "eyes", writer.close()))
    assert [o.shape for o in demo.behavior_spec.observation_specs] == [
        (3, 6, 7),
        (1, 4, 4),
        (5, 3, 3),
    ]
    seen = demo.steps[0].observations
    np.testing.assert_array_equal(seen[0], camera.astype(np.float32) / 255.0)
    np.testing.assert_allclose(seen[1], grey.astype(np.float32) / 255.0, atol=1e-7)
    np.testing.assert_array_equal(seen[2], grid.astype(np.float32) / 255.0)


def _saved(tmp_path, name, data):
    path = tmp_path / f"{name}.demo"
    path.write_bytes(data)
    return path


def _with_meta(demo, meta):
    from dataclasses import replace

    return replace(demo, meta=meta)
