"""The segment a worker sends: numpy arrays that become the learner's TensorDict."""

from __future__ import annotations

import numpy as np
import torch

from rollout import keys
from rollout.segments import Segment
from rollout.specs import spec_from_dict, spec_to_dict, step_spec
from tests.learners.fakes import segment as fake_segment
from tests.learners.fakes import vector_spec


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
