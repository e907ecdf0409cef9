"""Variable-length observations (a BufferSensor's padded rows) through the entity attention,
in the actor-critic, SAC's Q networks and POCA's group critic."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec, DimensionProperty, ObservationSpec
from mlagents_envs.base_env import ObservationType as Obs

from batches import keys
from learners.acting.factory import PolicyFactory
from learners.acting.numpy_policy import (
    acts_in_numpy,
    initial_entity_weights,
    initial_weights,
    trunk_input_width,
)
from learners.algorithms.ppo import PPO
from learners.algorithms.sac import SAC
from learners.networks.entities import present_rows
from learners.networks.group_critic import GroupCritic
from learners.networks.policies import ActorCritic, TorchActor
from learners.trainer_config.parse import defaults
from learners.trainer_config.settings import NetworkSettings
from testkit.segments import segment, vector_spec

ENTITIES, SIZE = 6, 5
VECTOR = ObservationSpec((4,), (DimensionProperty.NONE,), Obs.DEFAULT, "vector")
BUFFER = ObservationSpec(
    (ENTITIES, SIZE),
    (DimensionProperty.VARIABLE_SIZE, DimensionProperty.NONE),
    Obs.DEFAULT,
    "BufferSensor",
)
SPEC = BehaviorSpec([VECTOR, BUFFER], ActionSpec(0, (3, 3, 3)))  # Sorter's layout, smaller
SETTINGS = NetworkSettings(hidden_units=16, num_layers=2, normalize=True)


def rows(batch: int, present: list[int], seed: int = 0) -> torch.Tensor:
    """``[batch, ENTITIES, SIZE]`` with ``present[b]`` filled rows first, zeros after."""
    generator = torch.Generator().manual_seed(seed)
    out = torch.zeros(batch, ENTITIES, SIZE)
    for b, n in enumerate(present):
        out[b, :n] = torch.rand(n, SIZE, generator=generator) + 0.2
    return out


def network(spec: BehaviorSpec = SPEC, settings: NetworkSettings = SETTINGS) -> ActorCritic:
    return ActorCritic(spec, settings, initial_weights(spec, settings, np.random.default_rng(1)))


def test_padding_rows_are_absent_and_the_order_of_entities_does_not_matter():
    net = network()
    vector = torch.rand(3, 4)
    buffer = rows(3, [6, 2, 0])
    with torch.no_grad():
        encoded = net.encode({"vector": vector, "BufferSensor": buffer})
        shuffled = buffer.clone()
        shuffled[0] = buffer[0, torch.tensor([3, 1, 5, 0, 4, 2])]
        shuffled[1, 3:5] = buffer[1, :2]  # the same two entities, at other places
        shuffled[1, :2] = 0.0
        again = net.encode({"vector": vector, "BufferSensor": shuffled})
        torch.testing.assert_close(again, encoded)
        other = buffer.clone()
        other[1, 1] += 1.0  # a present entity changes: the encoding does
        moved = net.encode({"vector": vector, "BufferSensor": other})
    assert present_rows(buffer).sum(-1).tolist() == [6, 2, 0]
    assert encoded.shape == (3, trunk_input_width(SPEC, SETTINGS)) == (3, 4 + 128)
    assert torch.isfinite(encoded).all()  # no entity at all: the pooled attention is zeros
    torch.testing.assert_close(encoded[2, 4:], torch.zeros(128))
    assert not torch.allclose(moved[1], encoded[1]) and torch.equal(moved[0], encoded[0])


def test_the_buffer_is_never_normalized_and_its_weights_come_from_the_policy_factory():
    factory = PolicyFactory(default=SETTINGS, seed=3)
    state = factory.initial_weights("Sorter", SPEC)
    assert "encoders.1.norm.mean" not in state and "encoders.0.norm.mean" in state
    names = {k for k in state if k.startswith("entities.")}
    assert names == {
        f"entities.{layer}.{kind}"
        for layer in (
            "own.0",
            "embeddings.0.0",
            *(f"attention.{n}" for n in "qkv"),
            "attention.out",
        )
        for kind in ("weight", "bias")
    }
    assert state["entities.embeddings.0.0.weight"].shape == (128, 128 + SIZE)  # self, then row
    # the critic's own attention, as ML-Agents' separate critic has: the same layers, other draws
    critic = {k[7:]: v for k, v in state.items() if k.startswith("critic_entities.")}
    assert critic.keys() == names
    assert not np.array_equal(critic["entities.own.0.weight"], state["entities.own.0.weight"])
    # a behavior without a buffer keeps the very weights it had: no draw, no layer
    plain = vector_spec(4, 0, (3, 3, 3))
    rng = np.random.default_rng(0)
    drawn = rng.bit_generator.state
    assert initial_entity_weights(plain, SETTINGS, rng) == {}
    assert rng.bit_generator.state == drawn and network(plain).entities is None
    assert not acts_in_numpy(SPEC, SETTINGS) and acts_in_numpy(plain, SETTINGS)
    actor = factory("Sorter", SPEC)
    assert isinstance(actor, TorchActor)  # the worker acts through torch
    learner = factory.network("Sorter", SPEC)
    for name, value in learner.state_dict().items():
        if name in state:
            np.testing.assert_array_equal(value.numpy(), state[name])


def test_a_buffer_only_behavior_attends_without_a_self_encoding():
    spec = BehaviorSpec([BUFFER], ActionSpec(2, ()))
    net = network(spec)
    assert net.entities is not None and net.entities.own is None
    with torch.no_grad():
        out = net.encode({"BufferSensor": rows(2, [3, 1])})
    assert out.shape == (2, 128)


def test_ppo_and_sac_update_through_the_attention():
    batch = segment(SPEC, 4, 16)
    batch[keys.OBS, "BufferSensor"] = rows(64, [i % 7 for i in range(64)])
    batch[keys.NEXT, keys.OBS, "BufferSensor"] = rows(64, [(i + 1) % 7 for i in range(64)], 1)
    base = defaults("ppo")
    ppo = PPO(
        network(),
        replace(
            base,
            hyperparameters=replace(base.hyperparameters, buffer_size=32, batch_size=16),
            network_settings=SETTINGS,
        ),
    )
    before = {k: v.clone() for k, v in ppo.network.state_dict().items()}
    ppo.add(batch, torch.zeros(64, dtype=torch.int64))
    report = ppo.update(0.0)
    assert np.isfinite(report["Losses/Policy Loss"])
    after = ppo.network.state_dict()
    for name in ("entities.own.0.weight", "entities.attention.q.weight"):
        for owner in ("", "critic_"):  # the policy's loss one, the value loss the other
            assert not torch.equal(before[owner + name], after[owner + name]), owner + name
    with torch.no_grad():  # the critic's attention alone moves the value
        obs = {"vector": batch[keys.OBS, "vector"], "BufferSensor": batch[keys.OBS, "BufferSensor"]}
        value = ppo.network.state_value(obs)
        ppo.network.critic_entities.attention.out.weight.mul_(2.0)
        assert not torch.allclose(ppo.network.state_value(obs), value)
        actor = ppo.network.features(obs)
        ppo.network.critic_entities.own[0].weight.mul_(2.0)
        torch.testing.assert_close(ppo.network.features(obs), actor)
    sac_base = defaults("sac")
    sac_settings = replace(
        sac_base,
        hyperparameters=replace(sac_base.hyperparameters, batch_size=16, buffer_init_steps=0),
        network_settings=SETTINGS,
    )
    squashed = replace(SETTINGS, tanh_squash=True, conditional_sigma=True)
    sac = SAC(network(settings=squashed), sac_settings)
    assert all(q.entities is not None for q in sac.q)  # each Q attends on its own
    sac.add(batch, torch.zeros(64, dtype=torch.int64))
    losses = sac.gradient_step(sac.buffer.sample())
    assert all(torch.isfinite(v) for v in losses.values())


@pytest.mark.parametrize("mates", [0, 2])
def test_the_group_critic_attends_over_each_members_buffer(mates):
    critic = GroupCritic(SPEC, SETTINGS)
    assert critic.entities is not None
    obs = {"vector": torch.rand(3, 4), "BufferSensor": rows(3, [2, 5, 0])}
    mate_obs = {
        "vector": torch.rand(3, mates, 4),
        "BufferSensor": rows(3 * mates, [1] * 3 * mates).reshape(3, mates, ENTITIES, SIZE),
    }
    present = torch.ones(3, mates, dtype=torch.bool)
    with torch.no_grad():
        value = critic.value(obs, mate_obs, present)
        own = {**obs, "BufferSensor": obs["BufferSensor"].clone()}
        own["BufferSensor"][1, 0] += 1.0  # member 1's first entity
        moved = critic.value(own, mate_obs, present)
    assert value.shape == (3,) and torch.isfinite(value).all()
    assert moved[1] != value[1] and torch.equal(moved[[0, 2]], value[[0, 2]])
