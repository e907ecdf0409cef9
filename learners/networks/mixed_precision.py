"""The learner's mixed precision for dense layers: hidden layers in bfloat16, heads in float32.

Matrix products are nearly all of an MLP's update, and bfloat16 halves their cost where
the hardware has bfloat16 units: GPUs, and CPUs with AVX512-BF16 or AMX (on a Zen 4
core a 512-wide Swish MLP trains in half the time). Log-probabilities, values, losses and
the optimizer stay float32: an ``AutocastLayers`` hands its output on in float32, so the heads after
it, the PPO ratio and the value targets are computed as without mixed precision. Weights
and gradients stay float32 (autocast casts copies), so no loss scaling is needed.

A module that reads ``autocast`` gets it from ``devices.Compute.place``; elsewhere (a
worker's actor, an export) it is a no-op.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Any

import torch
from torch import nn

Autocast = Callable[[], AbstractContextManager[Any]]


class AutocastLayers(nn.Sequential):
    """Hidden layers run under the learner's autocast; float32 out, for the heads."""

    def __init__(self, *layers: nn.Module) -> None:
        super().__init__(*layers)
        self.autocast: Autocast = contextlib.nullcontext

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with self.autocast():
            return super().forward(x).float()


def set_autocast(network: nn.Module, autocast: Autocast) -> None:
    """Give every module of ``network`` that reads an ``autocast`` this one."""
    for module in network.modules():
        if hasattr(module, "autocast"):
            module.autocast = autocast
