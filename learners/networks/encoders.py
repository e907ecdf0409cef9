"""Image encoders by ``network_settings.vis_encode_type``: ML-Agents' five architectures.

Every type ends, as ML-Agents' do, in one dense layer to ``hidden_units`` (weights
``kaiming_normal`` with a linear gain, times 1.41; zero bias), so an image sensor's encoded
width is ``hidden_units`` whatever its size. Convolutions keep torch's default
initialization, as ML-Agents' do (drawn in numpy by ``learners.acting.numpy_images``, which is
also the workers' numpy form of these encoders). Each type has a smallest side its layers accept
(``MIN_SIZE``, ML-Agents' ``MIN_RESOLUTION_FOR_ENCODER``); a smaller image is a one-line
:class:`ImageTooSmall` naming the sensor, its size and what would fit.

Inputs are ``[..., C, H, W]``, float in [0, 1] or uint8 in [0, 255] (a player's PNG as stored);
uint8 becomes float / 255 here, on the input's device. Owned here: the architectures in torch. Not
owned: their minimum sizes and the size check (``learners.acting.numpy_images``, which workers
import without torch), vector sensors and the trunks (``learners.networks.policies``), the config
check of the type name (``learners.trainer_config.keys``).
"""

from __future__ import annotations

from functools import partial

import torch
from torch import nn

from learners.acting.numpy_images import DENSE_GAIN, MIN_SIZE, ImageTooSmall, check_size
from learners.networks.initializers import kaiming

__all__ = [
    "MIN_SIZE",
    "ImageTooSmall",
    "VisualEncoder",
    "check_size",
    "visual_encoder",
]


def _dense(width: int, out: int) -> nn.Linear:
    """ML-Agents' encoder head: kaiming_normal (linear gain) x 1.41."""
    return kaiming(width, out, DENSE_GAIN)


class ResidualBlock(nn.Module):
    """x + conv(swish(conv(swish(x)))), both 3x3 stride 1 padded: the shape is kept."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.layers = nn.Sequential(
            nn.SiLU(),
            nn.Conv2d(channels, channels, 3, 1, padding=1),
            nn.SiLU(),
            nn.Conv2d(channels, channels, 3, 1, padding=1),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.layers(x)


class VisualEncoder(nn.Module):
    """``body`` (convolutions, or nothing), flattened, then the dense head and its
    activation. Folds any leading axes beyond the batch (``[B, T, C, H, W]``)."""

    def __init__(
        self, body: nn.Module, shape: tuple[int, ...], out: int, activation: nn.Module
    ) -> None:
        super().__init__()
        with torch.no_grad():  # the flattened width, from the body itself
            flat = int(torch.flatten(body(torch.zeros(1, *shape)), 1).shape[1])
        self.body = body
        self.flat = flat
        self.size = out
        self.dense = _dense(flat, out)
        self.activation = activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dtype == torch.uint8:
            x = x.to(torch.float32) / 255.0
        if x.dim() > 4:
            lead = x.shape[:-3]
            return self.forward(x.reshape(-1, *x.shape[-3:])).reshape(*lead, -1)
        if x.is_cuda:  # cuDNN's fast kernels are NHWC (``devices.Compute.place``)
            x = x.contiguous(memory_format=torch.channels_last)
        return self.activation(self.dense(torch.flatten(self.body(x), 1)))


def _leaky_convs(
    layers: tuple[tuple[int, int, int], ...], channels: int
) -> tuple[nn.Module, nn.Module]:
    """Unpadded convolutions, ``(maps, kernel, stride)`` each, every one followed by a
    leaky ReLU; the dense head's activation: leaky ReLU."""
    modules: list[nn.Module] = []
    for maps, kernel, stride in layers:
        modules += [nn.Conv2d(channels, maps, kernel, stride), nn.LeakyReLU()]
        channels = maps
    return nn.Sequential(*modules), nn.LeakyReLU()


# ML-Agents' convolution stacks, (maps, kernel, stride) per layer
_SIMPLE = ((16, 8, 4), (32, 4, 2))
_NATURE_CNN = ((32, 8, 4), (64, 4, 2), (64, 3, 1))  # DQN's
_MATCH3 = ((35, 3, 1), (144, 3, 1))  # for small boards


def _resnet(channels: int) -> tuple[nn.Module, nn.Module]:
    """IMPALA's: three stacks (16, 32, 32 maps) of a padded 3x3 conv, a 3x3/2 max-pool and
    two residual blocks; swish; dense, ReLU."""
    layers: list[nn.Module] = []
    last = channels
    for maps in (16, 32, 32):
        layers += [nn.Conv2d(last, maps, 3, 1, padding=1), nn.MaxPool2d(3, 2)]
        layers += [ResidualBlock(maps), ResidualBlock(maps)]
        last = maps
    layers.append(nn.SiLU())
    return nn.Sequential(*layers), nn.ReLU()


def _fully_connected(channels: int) -> tuple[nn.Module, nn.Module]:
    """No convolution: every pixel into the dense layer, leaky ReLU."""
    return nn.Identity(), nn.LeakyReLU()


_BUILDERS = {
    "simple": partial(_leaky_convs, _SIMPLE),
    "nature_cnn": partial(_leaky_convs, _NATURE_CNN),
    "resnet": _resnet,
    "match3": partial(_leaky_convs, _MATCH3),
    "fully_connected": _fully_connected,
}


def visual_encoder(
    shape: tuple[int, ...], encoder_type: str, out: int, sensor: str = "image"
) -> VisualEncoder:
    """The ``encoder_type`` encoder of ``(C, H, W)`` images to ``out`` features (its
    weights from torch's random stream, which ``learners.acting.numpy_images`` draws again in
    numpy for every network); :class:`ImageTooSmall` below the minimum."""
    check_size(sensor, shape, encoder_type)
    body, activation = _BUILDERS[encoder_type](shape[0])
    return VisualEncoder(body, tuple(shape), out, activation)
