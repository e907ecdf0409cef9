"""ML-Agents' five image encoders (no Ray): layers, widths and parameter counts worked out by
hand from ML-Agents' architectures, the minimum sizes, uint8 input, SAC's Q encoders, and
tensors made on the input's device."""

from __future__ import annotations

import math

import pytest
import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec, ObservationSpec
from torch import nn

from learners.acting.factory import PolicyFactory
from learners.acting.numpy_policy import encoder_width, trunk_input_width
from learners.networks.encoders import MIN_SIZE, ImageTooSmall, ResidualBlock, visual_encoder
from learners.networks.policies import ActorCritic
from learners.networks.q_networks import QNetwork
from learners.networks.torchrl_views import ActionDistribution
from learners.trainer_config.keys import VIS_ENCODE_TYPES
from learners.trainer_config.settings import NetworkSettings
from testkit.segments import IMAGE, VECTOR


def image(shape: tuple[int, ...], name: str = "camera") -> ObservationSpec:
    return ObservationSpec(shape, IMAGE.dimension_property, IMAGE.observation_type, name)


def params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def convs(module: nn.Module) -> list[tuple[int, int, int, int, int]]:
    """(in, out, kernel, stride, padding) of every convolution, in order."""
    return [
        (m.in_channels, m.out_channels, m.kernel_size[0], m.stride[0], m.padding[0])
        for m in module.modules()
        if isinstance(m, nn.Conv2d)
    ]


def conv(c_in: int, c_out: int, kernel: int, *_stride_padding: int) -> int:
    return c_out * c_in * kernel * kernel + c_out  # weights and biases


RESNET_CONVS = [
    (3, 16, 3, 1, 1),
    *[(16, 16, 3, 1, 1)] * 4,
    (16, 32, 3, 1, 1),
    *[(32, 32, 3, 1, 1)] * 4,
    (32, 32, 3, 1, 1),
    *[(32, 32, 3, 1, 1)] * 4,
]
# (type, image, convolutions (in, out, kernel, stride, padding), flattened width), by hand
ARCHITECTURES = [
    # 84 -(8/4)-> 20 -(4/2)-> 9: 9 x 9 x 32
    ("simple", (3, 84, 84), [(3, 16, 8, 4, 0), (16, 32, 4, 2, 0)], 9 * 9 * 32),
    # 84 -(8/4)-> 20 -(4/2)-> 9 -(3/1)-> 7: 7 x 7 x 64 = 3136
    (
        "nature_cnn",
        (3, 84, 84),
        [(3, 32, 8, 4, 0), (32, 64, 4, 2, 0), (64, 64, 3, 1, 0)],
        3136,
    ),
    # padded convs keep the side, each 3/2 max-pool: 84 -> 41 -> 20 -> 9; 9 x 9 x 32
    ("resnet", (3, 84, 84), RESNET_CONVS, 9 * 9 * 32),
    # 8 -(3/1)-> 6 -(3/1)-> 4: 4 x 4 x 144
    ("match3", (6, 8, 8), [(6, 35, 3, 1, 0), (35, 144, 3, 1, 0)], 4 * 4 * 144),
    ("fully_connected", (3, 10, 10), [], 300),
]

# the totals at hidden_units 128, added up by hand (convolution weights + biases, dense)
PARAMETERS = {
    "simple": (16 * 3 * 64 + 16) + (32 * 16 * 16 + 32) + (2592 * 128 + 128),  # 343,216
    "nature_cnn": 6176 + 32832 + 36928 + (3136 * 128 + 128),  # 477,472
    # stacks: conv + two blocks of two 3x3 convs each (16, 32, 32 maps)
    "resnet": (448 + 4 * 2320) + (4640 + 4 * 9248) + (9248 + 4 * 9248) + 331904,  # 429,504
    "match3": (35 * 6 * 9 + 35) + (144 * 35 * 9 + 144) + (2304 * 128 + 128),  # 342,469
    "fully_connected": 300 * 128 + 128,  # 38,528
}


@pytest.mark.parametrize(
    ("kind", "shape", "layers", "flat"), ARCHITECTURES, ids=[a[0] for a in ARCHITECTURES]
)
def test_layers_widths_and_parameters_are_ml_agents(kind, shape, layers, flat):
    hidden = 128
    encoder = visual_encoder(shape, kind, hidden)
    assert convs(encoder) == layers
    assert encoder.flat == flat and encoder.size == hidden
    assert encoder.dense.weight.shape == (hidden, flat)
    expected = sum(conv(*layer) for layer in layers) + flat * hidden + hidden
    assert params(encoder) == expected == PARAMETERS[kind]
    assert encoder(torch.rand(3, *shape)).shape == (3, hidden)
    with torch.no_grad():
        assert torch.flatten(encoder.body(torch.rand(1, *shape)), 1).shape == (1, flat)


def test_activations_and_pooling_are_ml_agents():
    for kind, shape, count in (("simple", (3, 20, 20), 2), ("nature_cnn", (3, 36, 36), 3)):
        encoder = visual_encoder(shape, kind, 8)
        kinds = [type(m) for m in encoder.body]
        assert kinds == [nn.Conv2d, nn.LeakyReLU] * count, kind
        assert type(encoder.activation) is nn.LeakyReLU
    match3 = visual_encoder((1, 5, 5), "match3", 8)
    assert [type(m) for m in match3.body] == [nn.Conv2d, nn.LeakyReLU] * 2
    dense_only = visual_encoder((1, 1, 1), "fully_connected", 8)
    assert isinstance(dense_only.body, nn.Identity)
    assert type(dense_only.activation) is nn.LeakyReLU
    resnet = visual_encoder((3, 15, 15), "resnet", 8)
    body = list(resnet.body)
    stack = [nn.Conv2d, nn.MaxPool2d, ResidualBlock, ResidualBlock]
    assert [type(m) for m in body] == [*stack * 3, nn.SiLU]
    pools = [m for m in body if isinstance(m, nn.MaxPool2d)]
    assert all((p.kernel_size, p.stride, p.padding) == (3, 2, 0) for p in pools)
    block = body[2]
    assert [type(m) for m in block.layers] == [nn.SiLU, nn.Conv2d, nn.SiLU, nn.Conv2d]
    x = torch.rand(1, 16, 7, 7)
    with torch.no_grad():
        torch.testing.assert_close(block(x), x + block.layers(x))  # residual
    assert type(resnet.activation) is nn.ReLU


@pytest.mark.parametrize("kind", VIS_ENCODE_TYPES)
def test_the_dense_layer_starts_as_ml_agents_draws_it(kind):
    """kaiming_normal with a linear gain, times 1.41: std 1.41 / sqrt(fan in); zero bias."""
    torch.manual_seed(0)
    shape = {"match3": (1, 9, 9), "fully_connected": (3, 30, 30)}.get(kind, (3, 84, 84))
    dense = visual_encoder(shape, kind, 256).dense
    weight = dense.weight.detach()
    std = 1.41 / math.sqrt(weight.shape[1])
    assert abs(float(weight.std()) / std - 1.0) < 0.02
    assert abs(float(weight.mean())) < 5 * std / math.sqrt(weight.numel())
    assert not dense.bias.any()


def test_minimum_sizes_are_ml_agents():
    assert MIN_SIZE == {
        "simple": 20,
        "nature_cnn": 36,
        "resnet": 15,
        "match3": 5,
        "fully_connected": 1,
    }
    assert tuple(MIN_SIZE) == VIS_ENCODE_TYPES


@pytest.mark.parametrize("kind", VIS_ENCODE_TYPES)
def test_an_image_below_the_minimum_is_one_line_naming_sensor_size_and_fix(kind):
    low = MIN_SIZE[kind]
    settings = NetworkSettings(hidden_units=16, vis_encode_type=kind)
    accepted = BehaviorSpec([image((2, low, low + 3)), VECTOR], ActionSpec(1, (3,)))
    network = PolicyFactory({"Grid": settings}).network("Grid?team=0", accepted)
    obs = {"camera": torch.rand(4, 2, low, low + 3), "vector": torch.rand(4, 8)}
    assert network.act(obs)[0].shape == (4, 1)
    assert network.encoders[0](obs["camera"]).shape == (4, 16)
    if low == 1:
        return  # fully_connected takes any image
    for height, width in ((low - 1, low), (low, low - 1)):
        spec = BehaviorSpec([image((3, height, width), "CameraSensor")], ActionSpec(0, (5,)))
        with pytest.raises(ImageTooSmall) as caught:
            PolicyFactory({"GridWorld": settings}).network("GridWorld?team=0", spec)
        message = str(caught.value)
        fitting = [t for t in VIS_ENCODE_TYPES if MIN_SIZE[t] <= min(height, width)]
        assert message == (
            f"behavior GridWorld sensor CameraSensor is {height}x{width}, below {kind}'s "
            f"minimum of {low}x{low}: use vis_encode_type {' or '.join(fitting)}, or a "
            "larger image"
        )
        assert isinstance(caught.value, ValueError) and "\n" not in message
        with pytest.raises(ImageTooSmall, match=r"^sensor CameraSensor is "):
            ActorCritic(spec, settings)  # without the factory: the sensor, no behavior


@pytest.mark.parametrize("kind", VIS_ENCODE_TYPES)
def test_uint8_images_encode_as_float_over_255(kind):
    torch.manual_seed(1)
    encoder = visual_encoder((3, 40, 40), kind, 32)
    pixels = torch.randint(0, 256, (5, 3, 40, 40), dtype=torch.uint8)
    as_float = pixels.float() / 255
    with torch.no_grad():
        assert torch.equal(encoder(pixels), encoder(as_float))
        # [B, T, C, H, W] (a learner's batch): the time axis is folded and restored
        sequence = encoder(pixels.reshape(1, 5, 3, 40, 40))
    assert sequence.shape == (1, 5, 32)
    torch.testing.assert_close(sequence[0], encoder(as_float).detach())


def test_uint8_and_float_images_act_alike_through_the_network():
    spec = BehaviorSpec([image((3, 40, 40)), VECTOR], ActionSpec(2, (3,)))
    torch.manual_seed(0)
    network = ActorCritic(spec, NetworkSettings(hidden_units=32, vis_encode_type="resnet"))
    pixels = torch.randint(0, 256, (6, 3, 40, 40), dtype=torch.uint8)
    vector = torch.rand(6, 8)
    continuous, discrete, _ = network.act({"camera": pixels, "vector": vector})
    with torch.no_grad():
        a = network.evaluate({"camera": pixels, "vector": vector}, continuous, discrete)
        b = network.evaluate(
            {"camera": pixels.float() / 255, "vector": vector}, continuous, discrete
        )
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y)


@pytest.mark.parametrize("kind", VIS_ENCODE_TYPES)
def test_an_image_sensor_is_hidden_units_wide_in_the_trunk(kind):
    settings = NetworkSettings(hidden_units=48, num_layers=1, vis_encode_type=kind)
    spec = BehaviorSpec([image((3, 40, 40)), VECTOR], ActionSpec(1, ()))
    assert encoder_width((3, 40, 40), settings) == 48
    assert trunk_input_width(spec, settings) == 48 + 8
    network = ActorCritic(spec, settings)
    assert network.trunk[0].in_features == 56
    obs = {"camera": torch.rand(2, 3, 40, 40), "vector": torch.rand(2, 8)}
    assert network.encode(obs).shape == (2, 56)


@pytest.mark.parametrize("kind", ["nature_cnn", "match3"])
def test_sac_q_networks_encode_images_with_the_chosen_type(kind):
    settings = NetworkSettings(hidden_units=16, vis_encode_type=kind, tanh_squash=True)
    spec = BehaviorSpec([image((3, 36, 36)), VECTOR], ActionSpec(2, ()))
    network = ActorCritic(spec, settings)
    q = QNetwork(network, 1, action_size=2)
    assert convs(q.encoders[0]) == convs(network.encoders[0])
    assert params(q.encoders[0]) == params(network.encoders[0])
    assert q.encoders[0].size == 16 and q.body[0].in_features == 16 + 8 + 2
    pixels = torch.randint(0, 256, (4, 3, 36, 36), dtype=torch.uint8)
    assert q(pixels, torch.rand(4, 8), torch.rand(4, 2)).shape == (4, 1)


def test_tensors_made_while_acting_are_on_the_inputs_device():
    """The meta device stands in for a GPU: a tensor made on the CPU fails to mix with it."""
    spec = BehaviorSpec([image((3, 20, 20)), VECTOR], ActionSpec(2, (3, 2)))
    network = ActorCritic(spec, NetworkSettings(hidden_units=16)).to("meta")
    obs = {
        "camera": torch.zeros(4, 3, 20, 20, dtype=torch.uint8, device="meta"),
        "vector": torch.zeros(4, 8, device="meta"),
    }
    mask = torch.ones(4, 5, dtype=torch.bool, device="meta")
    continuous, discrete, log_prob = network.act(obs, mask)
    assert {continuous.device.type, discrete.device.type, log_prob.device.type} == {"meta"}
    outputs = network.evaluate(obs, continuous, discrete, mask)
    assert {t.device.type for t in outputs} == {"meta"}
    vector_only = ActorCritic(BehaviorSpec([VECTOR], ActionSpec(0, (3,)))).to("meta")
    _, picks, _ = vector_only.act({"vector": obs["vector"]})
    assert picks.device.type == "meta"
    for loc, logits, continuous_size, branches in (
        (torch.zeros(4, 2, device="meta"), None, 2, ()),
        (None, torch.zeros(4, 3, device="meta"), 0, (3,)),
    ):
        scale = torch.ones_like(loc) if loc is not None else None
        dist = ActionDistribution(loc, scale, logits, continuous=continuous_size, branches=branches)
        assert dist.entropy().device.type == "meta"
