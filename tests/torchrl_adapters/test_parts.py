"""The collector's parts without Ray: the key names torchrl reads, the queue that stands
in for the learner, and a user's TensorDictModule acting as a worker's policy."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec
from tensordict import TensorDict
from tensordict.nn import (
    InteractionType,
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
)
from torch import nn
from torchrl.modules import MaskedCategorical, NormalParamExtractor, TanhNormal

from batches import keys
from batches.segment import Segment
from testkit.segments import GRID, VECTOR, segment
from torchrl_adapters.batch_queue import ALL, BatchQueue
from torchrl_adapters.conventions import to_torchrl
from torchrl_adapters.module_actor import ModuleActor, ModuleActorFactory


def continuous_actor(obs: int, actions: int) -> nn.Module:
    net = TensorDictModule(
        nn.Sequential(nn.Linear(obs, 2 * actions), NormalParamExtractor()),
        in_keys=["observation"],
        out_keys=["loc", "scale"],
    )
    head = ProbabilisticTensorDictModule(
        in_keys=["loc", "scale"],
        out_keys=["action"],
        distribution_class=TanhNormal,
        return_log_prob=True,
        default_interaction_type=InteractionType.RANDOM,
    )
    return ProbabilisticTensorDictSequential(net, head)


def test_segments_take_torchrls_names_and_shapes():
    spec = BehaviorSpec([VECTOR, GRID], ActionSpec(2, (3, 2)))
    batch = to_torchrl(segment(spec, rows=3, steps=4, behavior="Soccer?team=1"))
    assert batch.batch_size == torch.Size([12])
    assert set(batch["observation"].keys()) == {"vector", "rank2"}  # several sensors: by name
    assert batch["observation", "rank2"].shape == (12, 2, 3)
    assert batch["action", "continuous"].shape == (12, 2)  # hybrid: both, by name
    assert batch["action", "discrete"].shape == (12, 2)
    torch.testing.assert_close(batch["action_log_prob"], torch.full((12,), -4.0))  # 4 parts
    for key in ("reward", "done", "terminated", "truncated", "group_reward"):
        assert batch["next", key].shape == (12, 1)
    assert batch["next", "done"].reshape(3, 4)[:, -1].all()  # each row ends done
    assert batch["team"].eq(1).all() and batch.get_non_tensor("behavior") == "Soccer?team=1"
    assert batch["action_mask"].shape == (12, 5)
    single = to_torchrl(segment(BehaviorSpec([VECTOR], ActionSpec(2, ())), 1, 3, "Ball"))
    assert single["observation"].shape == (3, 8) and single["action"].shape == (3, 2)
    assert single["team"].eq(0).all() and "action_mask" not in single


def part(behavior: str, n: int, source: tuple[str, int] | None = None) -> Segment:
    data = {keys.POLICY_VERSION: np.zeros(n, np.int64)}
    return Segment(behavior, {}, data, source)


def test_the_queue_asks_for_one_batch_and_takes_each_source_once():
    queue = BatchQueue(frames_per_batch=100)
    assert queue.submit([]) == (0, 100)
    assert queue.submit([part("A?team=0", 60, ("w", 1))]) == (0, 40)
    assert queue.take() is None  # not a batch yet
    assert queue.submit([part("A?team=0", 60, ("w", 1))]) == (0, 40)  # Ray's retry: dropped
    assert queue.submit([part("A?team=0", 20, ("w", 2)), part("B?team=1", 30, ("w", 2))]) == (
        0,
        0,
    )  # one collect, two behaviors: each taken; a batch, no more now
    taken = queue.take()
    assert [len(s) for s in taken] == [60, 20, 30] and queue.wanted() == 100
    only = BatchQueue(frames_per_batch=10, behavior="B")
    only.submit([part("A?team=0", 30), part("B?team=0", 4)])
    assert only.steps == 4 and only.seen == ["A?team=0", "B?team=0"]


def test_published_weights_reach_every_behavior_met_even_one_met_later():
    queue = BatchQueue(frames_per_batch=10)
    queue.submit([part("A?team=0", 1)])
    assert queue.publish({ALL: {"w": np.ones(2)}}) == 1
    version, weights = queue.weights()
    assert version == 1 and list(weights) == ["A?team=0"]
    version, _ = queue.submit([part("B?team=0", 1)])  # met after the weights: a new version
    assert version == 2 and list(queue.weights()[1]) == ["A?team=0", "B?team=0"]
    queue.publish({"A": {"w": np.zeros(2)}})  # by behavior name: B has none
    assert list(queue.weights()[1]) == ["A?team=0"]


def test_a_users_module_acts_as_a_workers_policy():
    torch.manual_seed(0)
    spec = BehaviorSpec([VECTOR], ActionSpec(2, ()))
    module = continuous_actor(8, 2)
    actor = ModuleActorFactory(module)("Ball?team=0", spec)
    assert actor.module is not module  # each behavior its own copy
    obs = np.random.default_rng(0).standard_normal((5, 8), dtype=np.float32)
    continuous, discrete, log_prob = actor.act({"vector": obs})
    assert continuous.shape == (5, 2) and discrete.shape == (5, 0) and log_prob.shape == (5, 2)
    assert np.abs(continuous).max() <= 1.0  # TanhNormal: as the module wrote it
    dist = module.get_dist(TensorDict({"observation": torch.from_numpy(obs)}, [5]))
    expected = dist.log_prob(torch.from_numpy(continuous))
    np.testing.assert_allclose(log_prob.sum(1), expected.detach().numpy(), rtol=1e-4, atol=1e-4)
    assert (log_prob[:, 1] == 0).all()  # the action's log-probability in the first place
    state = {k: v * 0 for k, v in module.state_dict().items()}
    actor.load_state_dict({k: v.numpy() for k, v in state.items()})
    assert all(v.eq(0).all() for v in actor.module.state_dict().values())


def test_a_discrete_module_sees_the_action_mask():
    spec = BehaviorSpec([VECTOR], ActionSpec(0, (3,)))
    logits = TensorDictModule(nn.Linear(8, 3), in_keys=["observation"], out_keys=["logits"])
    head = ProbabilisticTensorDictModule(
        in_keys={"logits": "logits", "mask": "action_mask"},
        out_keys=["action"],
        distribution_class=MaskedCategorical,
        return_log_prob=True,
    )
    actor = ModuleActor(ProbabilisticTensorDictSequential(logits, head), spec)
    mask = np.array([[True, False, False]] * 50 + [[False, True, True]] * 50)
    obs = np.random.default_rng(1).standard_normal((100, 8), dtype=np.float32)
    _, discrete, log_prob = actor.act({"vector": obs}, mask)
    assert discrete.shape == (100, 1)
    assert (discrete[:50, 0] == 0).all() and (discrete[50:, 0] > 0).all()  # never masked
    assert (log_prob[:50, 0] == 0).all()  # the only allowed action: certain


def test_a_policy_per_behavior_names_a_missing_one():
    factory = ModuleActorFactory({"A": continuous_actor(8, 2)})
    with pytest.raises(KeyError, match="behavior B: no policy given for it"):
        factory("B?team=0", BehaviorSpec([VECTOR], ActionSpec(2, ())))
