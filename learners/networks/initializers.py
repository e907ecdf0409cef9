"""ML-Agents' weight initialisers for the torch layers that draw their own (image encoder
heads, POCA's critic, the reward signals' networks): one home, so a layer initialised "as
ML-Agents does" means the same thing everywhere. The actor-critic's weights are drawn in
numpy by the policy factory instead (``learners.acting``), so that a worker and the learner
start from the very same policy."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

__all__ = ["kaiming", "normal", "xavier"]


def kaiming(fan_in: int, out: int, gain: float = 1.0) -> nn.Linear:
    """ML-Agents' ``linear_layer`` with ``KaimingHeNormal``: std 1/sqrt(fan in) times
    ``gain``, zero bias."""
    return _linear(fan_in, out, lambda w: nn.init.kaiming_normal_(w, nonlinearity="linear"), gain)


def xavier(fan_in: int, out: int, gain: float = 1.0) -> nn.Linear:
    """ML-Agents' ``linear_layer`` with ``XavierGlorotUniform`` times ``gain``, zero bias."""
    return _linear(fan_in, out, nn.init.xavier_uniform_, gain)


def normal(fan_in: int, out: int, gain: float = 1.0) -> nn.Linear:
    """ML-Agents' ``Initialization.Normal`` (std 1) times ``gain``, zero bias."""
    return _linear(fan_in, out, nn.init.normal_, gain)


def _linear(
    fan_in: int, out: int, draw: Callable[[torch.Tensor], object], gain: float
) -> nn.Linear:
    """A linear layer whose weights ``draw`` fills, then scales by ``gain``; zero bias."""
    layer = nn.Linear(fan_in, out)
    draw(layer.weight)
    with torch.no_grad():
        layer.weight.mul_(gain)
    nn.init.zeros_(layer.bias)
    return layer
