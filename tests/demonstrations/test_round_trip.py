"""Our writer, then our reader: every field of every step comes back."""

import dataclasses

import numpy as np
import pytest

from demonstrations import DemoError, DemoMeta, Demonstration, DemoStep, read_demo, write_demo
from tests.demonstrations import samples


@pytest.mark.parametrize("name", ["DISCRETE", "CONTINUOUS", "HYBRID"])
def test_vector_and_float_observations_round_trip_exactly(tmp_path, name):
    demo = samples.demonstration(getattr(samples, name))
    path = tmp_path / "expert.demo"
    write_demo(path, demo)
    assert read_demo(path) == demo


def test_the_round_trip_keeps_actions_masks_and_episode_ends(tmp_path):
    demo = samples.demonstration(samples.DISCRETE, count=10)
    write_demo(tmp_path / "a.demo", demo)
    back = read_demo(tmp_path / "a.demo")
    assert [s.done for s in back.steps] == [i % 5 == 4 for i in range(10)]
    assert [s.interrupted for s in back.steps] == [i == 9 for i in range(10)]
    assert [s.agent_id for s in back.steps] == [7] * 5 + [8] * 5
    for ours, theirs in zip(demo.steps, back.steps, strict=True):
        assert ours.discrete.dtype == theirs.discrete.dtype == np.int32
        np.testing.assert_array_equal(ours.discrete, theirs.discrete)
        np.testing.assert_array_equal(ours.action_mask, theirs.action_mask)
        assert theirs.action_mask.shape == (5,) and theirs.continuous.size == 0
    assert back.behavior_spec == samples.DISCRETE
    assert back.behavior_name == "Walker?team=0"


def test_the_summary_counts_steps_episodes_and_mean_reward(tmp_path):
    demo = samples.demonstration(samples.CONTINUOUS, count=12)  # two episodes and a part
    assert (demo.meta.steps, demo.meta.episodes) == (12, 3)
    total = np.float32(0)
    for step in demo.steps:
        total = np.float32(total + np.float32(step.reward))
    assert demo.meta.mean_reward == pytest.approx(float(total) / 3, rel=1e-6)
    write_demo(tmp_path / "a.demo", demo)
    assert read_demo(tmp_path / "a.demo").meta == demo.meta


def test_png_observations_round_trip(tmp_path):
    demo = samples.demonstration(samples.IMAGES, pixels=True)
    path = tmp_path / "images.demo"
    write_demo(path, demo, png=[0, 1, 2])
    data = path.read_bytes()
    assert data.count(b"\x89PNG\r\n\x1a\n") == len(demo.steps) * (1 + 1 + 2)
    back = read_demo(path)
    assert back.behavior_spec == demo.behavior_spec
    for ours, theirs in zip(demo.steps, back.steps, strict=True):
        for a, b in zip(ours.observations, theirs.observations, strict=True):
            # exact but for the greyscale mean of three equal floats (an ulp, as ML-Agents)
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-7)
        assert dataclasses.replace(theirs, observations=ours.observations) == ours


def test_png_is_only_for_images_in_0_to_1(tmp_path):
    with pytest.raises(DemoError, match="sensors \\[0\\] cannot be PNGs"):
        write_demo(tmp_path / "a.demo", samples.demonstration(samples.DISCRETE), png=[0])
    demo = samples.demonstration(samples.IMAGES, count=3, pixels=True)
    bright = dataclasses.replace(
        demo.steps[2],
        observations=(demo.steps[2].observations[0] * 2, *demo.steps[2].observations[1:]),
    )
    with pytest.raises(DemoError, match="step 2: a PNG sensor with values outside"):
        write_demo(
            tmp_path / "a.demo", dataclasses.replace(demo, steps=(*demo.steps[:2], bright)), png=[0]
        )


def test_values_are_immutable():
    demo = samples.demonstration(samples.DISCRETE, count=2)
    step = demo.steps[0]
    with pytest.raises(ValueError, match="read-only"):
        step.observations[0][0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        step.discrete[0] = 1
    with pytest.raises(dataclasses.FrozenInstanceError):
        step.reward = 2.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        demo.meta = DemoMeta("x", 0, 0, 0.0)
    assert isinstance(demo.steps, tuple)


def test_steps_take_copies_of_the_callers_arrays():
    observation = np.zeros(3, np.float32)
    step = DemoStep(observations=(observation,), discrete=[1, 2])
    observation[0] = 5.0
    assert step.observations[0][0] == 0.0
    assert step == DemoStep(observations=(np.zeros(3),), discrete=np.array([1, 2]))
    assert step != DemoStep(observations=(np.zeros(3),), discrete=[1, 3])


def test_a_demonstration_is_equal_by_value():
    a = samples.demonstration(samples.HYBRID, count=3)
    b = samples.demonstration(samples.HYBRID, count=3)
    assert a == b
    assert a != Demonstration(a.meta, a.behavior_name, a.behavior_spec, a.steps[:2])
