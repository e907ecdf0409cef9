"""The segment a worker sends: numpy arrays that become the learner's TensorDict."""

from __future__ import annotations

import numpy as np
import torch

from batches import keys
from batches.segment import Segment
from batches.specs import spec_from_dict, spec_to_dict, step_spec
from testkit.segments import segment as fake_segment
from testkit.segments import vector_spec


def numpy_segment(steps: int, first_version: int = 0) -> Segment:
    """A well-formed segment (the learner tests' fake, as a worker would send it)."""
    spec = vector_spec(continuous=2, branches=(3,))
    batch = fake_segment(spec, 1, steps)
    batch[keys.POLICY_VERSION] = torch.arange(first_version, first_version + steps)
    return Segment(
        "B?team=0", spec_to_dict(spec), as_numpy(batch.exclude(*keys.METADATA).to_dict())
    )


def as_numpy(tree: dict) -> dict:
    return {k: as_numpy(v) if isinstance(v, dict) else v.numpy() for k, v in tree.items()}


def test_the_learner_view_shares_writable_arrays_and_copies_read_only_ones():
    segment = numpy_segment(4)
    batch = segment.to_tensordict()
    spec = spec_from_dict(segment.spec)
    assert step_spec(spec).expand(4).is_in(batch.exclude(*keys.METADATA))
    assert batch.get_non_tensor(keys.BEHAVIOR) == "B?team=0"
    assert batch.get_non_tensor(keys.SPEC) == segment.spec
    versions = segment.data[keys.POLICY_VERSION]
    versions[0] = 7  # the same memory
    assert int(batch[keys.POLICY_VERSION][0]) == 7
    # Ray's object store hands arrays over read-only: the learner gets a writable copy
    # (torch would warn, and an in-place op would be undefined).
    reward = segment.data[keys.NEXT][keys.REWARD]
    reward.flags.writeable = False
    again = segment.to_tensordict()
    again[keys.NEXT, keys.REWARD].add_(1.0)
    np.testing.assert_array_equal(again[keys.NEXT, keys.REWARD].numpy(), reward + 1.0)


def test_segments_of_a_behavior_concatenate_in_order():
    parts = [numpy_segment(3, first_version=0), numpy_segment(2, first_version=10)]
    joined = Segment.concat(parts)
    assert len(joined) == 5 and Segment.concat(parts[:1]) is parts[0]
    assert joined.data[keys.POLICY_VERSION].tolist() == [0, 1, 2, 10, 11]
    assert joined.nbytes == sum(p.nbytes for p in parts) > 0
    np.testing.assert_array_equal(
        joined.data[keys.OBS]["vector"],
        np.concatenate([p.data[keys.OBS]["vector"] for p in parts]),
    )


def test_png_sensors_are_kept_as_exact_uint8_and_vectors_as_float32():
    """Unity's PNG images decode to k/255: the worker keeps k (a quarter of the bytes),
    exactly, and the learner's spec says uint8 for them."""
    from mlagents_envs.base_env import (
        ActionSpec,
        BehaviorSpec,
        DecisionSteps,
        DimensionProperty,
        ObservationSpec,
        ObservationType,
        TerminalSteps,
    )

    from rollout.collecting.decisions import Decisions
    from rollout.collecting.segments import SegmentBuilder

    plain = (DimensionProperty.NONE,)
    image = (
        DimensionProperty.NONE,
        DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,
        DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,
    )
    spec = BehaviorSpec(
        [
            ObservationSpec((3, 5, 4), image, ObservationType.DEFAULT, "Camera"),
            ObservationSpec((2,), plain, ObservationType.DEFAULT, "Velocity"),
        ],
        ActionSpec.create_discrete((3,)),
    )
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (3, 2, 3, 5, 4)).astype(np.uint8)  # 3 exchanges, 2 agents
    velocity = rng.normal(size=(3, 2, 2)).astype(np.float32)
    ids = np.array([4, 9], np.int32)
    builder = SegmentBuilder("B?team=0", spec, horizon=2, pixel_sensors=frozenset({"Camera"}))
    no_terminals = TerminalSteps.empty(spec)
    chosen = Decisions(
        np.zeros((2, 0), np.float32), np.ones((2, 1), np.int64), np.zeros((2, 1), np.float32)
    )
    for t in range(3):
        decoded = frames[t].astype(np.float32) / np.float32(255.0)  # mlagents' PNG decode
        decisions = DecisionSteps(
            [decoded, velocity[t]],
            np.zeros(2, np.float32),
            ids,
            None,
            np.zeros(2, np.int32),
            np.zeros(2, np.float32),
        )
        builder.observe(decisions, no_terminals)
        segment = builder.collect()
        builder.act(decisions, chosen, policy_version=t)
    assert segment is not None and len(segment) == 4  # two rows of the horizon, 2 steps each
    obs, nxt = segment.data[keys.OBS], segment.data[keys.NEXT][keys.OBS]
    assert obs["Camera"].dtype == np.uint8 and nxt["Camera"].dtype == np.uint8
    assert obs["Velocity"].dtype == np.float32
    np.testing.assert_array_equal(obs["Camera"][[0, 2]], frames[0])  # packed: agent 4, agent 9
    np.testing.assert_array_equal(nxt["Camera"][[1, 3]], frames[2])
    np.testing.assert_array_equal(obs["Velocity"][[0, 2]], velocity[0])
    batch = segment.to_tensordict()
    assert step_spec(spec, {"Camera"}).expand(4).is_in(batch.exclude(*keys.METADATA))
    assert not step_spec(spec).expand(4).is_in(batch.exclude(*keys.METADATA))
    image_bytes = obs["Camera"].nbytes + nxt["Camera"].nbytes
    assert image_bytes * 4 == 2 * 4 * 3 * 5 * 4 * 4  # float32 would be 4x


def test_a_row_cut_at_the_horizon_is_marked_cut_and_an_interrupted_end_is_not():
    """Both are ``truncated`` (the learner bootstraps at either); only the cut leaves the
    episode going on (``("next", "cut")``), so per-episode figures end at the other."""
    from mlagents_envs.base_env import DecisionSteps, TerminalSteps

    from rollout.collecting.decisions import Decisions
    from rollout.collecting.segments import SegmentBuilder

    spec = vector_spec(2, branches=(3,))
    builder = SegmentBuilder("B?team=0", spec, horizon=3)
    ids = np.array([7], np.int32)
    obs = [np.zeros((1, 2), np.float32)]
    chosen = Decisions(np.zeros((1, 0), np.float32), np.ones((1, 1), np.int64), np.zeros((1, 1)))
    zero, group = np.zeros(1, np.float32), np.zeros(1, np.int32)
    decision = DecisionSteps(obs, zero, ids, None, group, zero)
    none = TerminalSteps.empty(spec)
    interrupted = TerminalSteps(obs, zero, np.ones(1, bool), ids, group, zero)
    rows = []
    for t in range(6):  # decisions at 0..4, the episode interrupted at exchange 5
        ending = t == 5
        if ending:
            builder.observe(DecisionSteps.empty(spec), interrupted)
        else:
            builder.observe(decision, none)
        if (segment := builder.collect()) is not None:
            rows.append(segment)
        if not ending:
            builder.act(decision, chosen, policy_version=t)
    segment = Segment.concat(rows)
    nxt = segment.data[keys.NEXT]
    assert len(segment) == 5  # a row of the horizon (3 steps), then one of 2 to the end
    assert nxt[keys.TRUNCATED][:, 0].tolist() == [False, False, True, False, True]
    assert nxt[keys.DONE][:, 0].tolist() == [False, False, True, False, True]
    assert nxt[keys.CUT][:, 0].tolist() == [False, False, True, False, False]
