"""PPO's minibatch step: the graph's inputs, checkpoints across optimizer kinds, and (on a
machine with CUDA) a graphed update against the eager one."""

from __future__ import annotations

import pytest
import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec, DimensionProperty, ObservationSpec
from mlagents_envs.base_env import ObservationType as Obs

from learners.algorithms.minibatch import (
    adam,
    load_optimizer,
    plain_learning_rates,
    set_learning_rate,
)
from learners.algorithms.ppo import PPO
from learners.host.devices import Compute
from learners.networks.encoders import visual_encoder
from learners.networks.policies import ActorCritic
from learners.trainer_config.settings import NetworkSettings
from testkit.segments import VECTOR, segment
from tests.learners.test_algorithms import settings

CUDA = torch.cuda.is_available()
IMAGE_84 = ObservationSpec(
    (3, 84, 84),
    (DimensionProperty.NONE, *(DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,) * 2),
    Obs.DEFAULT,
    "camera",
)


def test_a_checkpoint_of_a_gpu_optimizer_loads_into_a_cpu_one_and_back():
    """A GPU's Adam has a tensor learning rate and is capturable; a checkpoint keeps plain
    numbers, and loading keeps the loading optimizer's own kind with the saved state."""
    layer = torch.nn.Linear(3, 2)
    cpu = adam(layer.parameters(), 1e-3, Compute("cpu"))
    layer(torch.ones(1, 3)).sum().backward()
    cpu.step()
    saved = cpu.state_dict()
    gpu_like = {
        **saved,
        "param_groups": [
            {**g, "lr": torch.tensor(5e-4), "capturable": True} for g in saved["param_groups"]
        ],
    }
    plain = plain_learning_rates(gpu_like)
    assert plain["param_groups"][0]["lr"] == pytest.approx(5e-4)
    assert isinstance(plain["param_groups"][0]["lr"], float)

    other = torch.nn.Linear(3, 2)
    fresh = adam(other.parameters(), 1e-3, Compute("cpu"))
    load_optimizer(fresh, gpu_like)
    group = fresh.param_groups[0]
    assert group["lr"] == pytest.approx(5e-4) and not group["capturable"] and group["fused"]
    assert torch.equal(fresh.state[other.weight]["exp_avg"], cpu.state[layer.weight]["exp_avg"])
    other(torch.ones(1, 3)).sum().backward()
    fresh.step()  # the loaded state steps on the CPU

    rate = torch.tensor(1e-3)  # a tensor learning rate is written in place (a graph reads it)
    tensor_lr = torch.optim.Adam(torch.nn.Linear(1, 1).parameters(), lr=rate)
    set_learning_rate(tensor_lr, 2e-4)
    assert tensor_lr.param_groups[0]["lr"] is rate and float(rate) == pytest.approx(2e-4)


def test_a_ppo_checkpoint_goes_on_where_it_stopped():
    spec = BehaviorSpec([VECTOR], ActionSpec(2, ()))
    torch.manual_seed(0)
    first = PPO(ActorCritic(spec), settings(batch_size=16, buffer_size=32))
    first.add(segment(spec, 3, 16), torch.zeros(48, dtype=torch.int64))
    first.update(progress=0.5)
    second = PPO(ActorCritic(spec), settings(batch_size=16, buffer_size=32))
    second.load_state_dict(first.state_dict())
    state = second.optimizer.state_dict()["state"]
    assert all(float(s["step"]) == 9 for s in state.values())  # 3 epochs of 3 minibatches
    assert isinstance(first.state_dict()["optimizer"]["param_groups"][0]["lr"], float)


def test_channels_last_weights_and_inputs_compute_the_same_features():
    """On a GPU the encoders run channels-last (``Compute.place``); flattening must still
    read the features in the order the dense layer was trained on."""
    for kind in ("simple", "nature_cnn", "resnet"):
        torch.manual_seed(1)
        encoder = visual_encoder((3, 84, 84), kind, 32, "camera")
        x = torch.rand(4, 3, 84, 84)
        expected = encoder(x)
        encoder.to(memory_format=torch.channels_last)
        got = encoder(x.contiguous(memory_format=torch.channels_last))
        torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5)


@pytest.mark.skipif(not CUDA, reason="needs CUDA")
@pytest.mark.parametrize("image", [False, True])
def test_a_graphed_update_trains_as_the_eager_one(image):
    spec = BehaviorSpec([IMAGE_84, VECTOR] if image else [VECTOR], ActionSpec(2, (3,)))
    network = NetworkSettings(hidden_units=32, num_layers=2, vis_encode_type="nature_cnn")
    compute = Compute.of("cuda")
    weights = []
    for graphed in (True, False):
        torch.manual_seed(0)
        net = ActorCritic(spec, network)
        compute.place(net)
        ppo = PPO(net, settings(batch_size=32, buffer_size=64), compute)
        ppo.step.graphable = graphed
        torch.manual_seed(1)
        for seed in range(4):
            ppo.add(segment(spec, 5, 16, seed=seed), torch.zeros(80, dtype=torch.int64))
            report = ppo.update(progress=0.1)
        assert (ppo.step._graph is not None) == graphed
        weights.append({k: v.float().cpu() for k, v in net.state_dict().items()})
        losses = report["Losses/Policy Loss"], report["Losses/Value Loss"]
        assert all(torch.isfinite(torch.tensor(losses)))
    for key, value in weights[0].items():
        torch.testing.assert_close(value, weights[1][key], rtol=1e-3, atol=1e-4, msg=key)
