"""ML-Agents' image encoders in numpy, so that a worker with a camera acts without torch.

A worker that loads torch to act is 700-800 MB resident; one that acts in numpy stays
near a vector worker's 124 MB. ``learners.networks.encoders`` is the learner's (torch) form of the
same five architectures; both name their weights alike (``body.K.weight``,
``dense.weight``), so the learner's published state loads here as it is, and the tests
hold the two forms to the same outputs.

The encoders' initial weights are drawn here too, with torch's default laws (a
convolution's weight and bias uniform in +-1/sqrt(fan in); the dense head
``kaiming_normal`` with a linear gain, times 1.41, zero bias), so workers and learner
start from the same weights without torch.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from learners.trainer_config.keys import VIS_ENCODE_TYPES

# smallest height and width each type's layers accept (ML-Agents' values)
MIN_SIZE: dict[str, int] = {
    "simple": 20,
    "nature_cnn": 36,
    "resnet": 15,
    "match3": 5,
    "fully_connected": 1,
}
assert tuple(MIN_SIZE) == VIS_ENCODE_TYPES, "every configurable type has a minimum"


class ImageTooSmall(ValueError):
    """An image sensor smaller than its encoder's minimum; the message is one line."""


def check_size(sensor: str, shape: tuple[int, ...], encoder_type: str) -> None:
    """Raise :class:`ImageTooSmall` when ``shape`` ``(C, H, W)`` is below the type's minimum,
    naming the types that would take it (so the fix is in the message)."""
    if encoder_type not in MIN_SIZE:
        raise ValueError(
            f"vis_encode_type: expected one of {', '.join(MIN_SIZE)}, got {encoder_type!r}"
        )
    _, height, width = shape
    minimum = MIN_SIZE[encoder_type]
    if min(height, width) >= minimum:
        return
    fitting = [t for t, size in MIN_SIZE.items() if size <= min(height, width)]
    fix = f"use vis_encode_type {' or '.join(fitting)}, or " if fitting else "use "
    raise ImageTooSmall(
        f"sensor {sensor} is {height}x{width}, below {encoder_type}'s minimum of "
        f"{minimum}x{minimum}: {fix}a larger image"
    )


LEAKY_SLOPE = 0.01  # torch's LeakyReLU default, as ML-Agents uses it
DENSE_GAIN = 1.41  # ML-Agents' ReLU gain on the encoders' dense layer
# (maps, kernel, stride) per unpadded convolution, each followed by a leaky ReLU
LEAKY_CONVS = {
    "simple": ((16, 8, 4), (32, 4, 2)),
    "nature_cnn": ((32, 8, 4), (64, 4, 2), (64, 3, 1)),
    "match3": ((35, 3, 1), (144, 3, 1)),
    "fully_connected": (),
}
RESNET_STACKS = (16, 32, 32)  # a padded 3x3 conv, a 3x3/2 max-pool, two residual blocks each


def _conv_out(size: int, kernel: int, stride: int, pad: int = 0) -> int:
    return (size + 2 * pad - kernel) // stride + 1


def initial_encoder_weights(
    prefix: str,
    shape: tuple[int, ...],
    encoder_type: str,
    out: int,
    rng: np.random.Generator,
    sensor: str = "image",
) -> dict[str, np.ndarray]:
    """The encoder's weights under ``prefix`` (``encoders.I.net``), as torch would draw
    them; ``shape`` is ``(C, H, W)``. Below the type's minimum size: ``ImageTooSmall``."""
    check_size(sensor, shape, encoder_type)
    state: dict[str, np.ndarray] = {}
    channels, height, width = shape

    def conv(name: str, c_in: int, c_out: int, kernel: int) -> None:
        bound = 1.0 / math.sqrt(c_in * kernel * kernel)
        weight = rng.uniform(-bound, bound, size=(c_out, c_in, kernel, kernel))
        state[f"{prefix}.{name}.weight"] = weight.astype(np.float32)
        state[f"{prefix}.{name}.bias"] = rng.uniform(-bound, bound, c_out).astype(np.float32)

    if encoder_type == "resnet":
        index = 0
        for maps in RESNET_STACKS:
            conv(f"body.{index}", channels, maps, 3)
            height, width = _conv_out(height, 3, 2), _conv_out(width, 3, 2)
            for block in (index + 2, index + 3):
                conv(f"body.{block}.layers.1", maps, maps, 3)
                conv(f"body.{block}.layers.3", maps, maps, 3)
            channels, index = maps, index + 4
    else:
        for layer, (maps, kernel, stride) in enumerate(LEAKY_CONVS[encoder_type]):
            conv(f"body.{2 * layer}", channels, maps, kernel)
            height, width = _conv_out(height, kernel, stride), _conv_out(width, kernel, stride)
            channels = maps
    flat = channels * height * width
    dense = rng.normal(0.0, 1.0 / math.sqrt(flat), size=(out, flat)) * DENSE_GAIN
    state[f"{prefix}.dense.weight"] = dense.astype(np.float32)
    state[f"{prefix}.dense.bias"] = np.zeros(out, np.float32)
    return state


class NumpyImageEncoder:
    """One image sensor's encoder, ``[n, C, H, W]`` (uint8 or float) to ``[n, out]``."""

    def __init__(self, encoder_type: str, state: Mapping[str, np.ndarray]) -> None:
        self.encoder_type = encoder_type
        self.state = {k: np.asarray(v, np.float32) for k, v in state.items()}

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = x.astype(np.float32) / 255.0 if x.dtype == np.uint8 else x.astype(np.float32)
        if self.encoder_type == "resnet":
            x = self._resnet(x)
        else:
            for layer, (_, _, stride) in enumerate(LEAKY_CONVS[self.encoder_type]):
                x = _leaky(self._conv(f"body.{2 * layer}", x, stride))
        hidden = x.reshape(len(x), -1) @ self.state["dense.weight"].T + self.state["dense.bias"]
        if self.encoder_type == "resnet":
            return np.maximum(hidden, 0.0)
        return _leaky(hidden)

    def _resnet(self, x: np.ndarray) -> np.ndarray:
        index = 0
        for _ in RESNET_STACKS:
            x = self._conv(f"body.{index}", x, 1, pad=1)
            x = sliding_window_view(x, (3, 3), axis=(2, 3))[:, :, ::2, ::2].max(axis=(-2, -1))
            for block in (index + 2, index + 3):
                inner = self._conv(f"body.{block}.layers.1", _swish(x), 1, pad=1)
                x = x + self._conv(f"body.{block}.layers.3", _swish(inner), 1, pad=1)
            index += 4
        return _swish(x)

    def _conv(self, name: str, x: np.ndarray, stride: int, pad: int = 0) -> np.ndarray:
        weight, bias = self.state[f"{name}.weight"], self.state[f"{name}.bias"]
        kernel = weight.shape[-1]
        if pad:
            x = np.pad(x, ((0, 0), (0, 0), (pad, pad), (pad, pad)))
        windows = sliding_window_view(x, (kernel, kernel), axis=(2, 3))[:, :, ::stride, ::stride]
        out = np.tensordot(windows, weight, axes=([1, 4, 5], [1, 2, 3]))  # [n, h, w, maps]
        return np.ascontiguousarray((out + bias).transpose(0, 3, 1, 2))


def _leaky(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x, LEAKY_SLOPE * x)


def _swish(x: np.ndarray) -> np.ndarray:
    return x * (0.5 * (1.0 + np.tanh(0.5 * x)))  # x sigmoid(x), without overflow
