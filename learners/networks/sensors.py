"""Each sensor's encoder: vectors as they are (optionally normalized by running statistics),
images and grids through ML-Agents' ``vis_encode_type`` encoder (``learners.networks.encoders``).
The actor-critic (``learners.networks.policies``), SAC's critics and POCA's group critic each build
one per sensor."""

from __future__ import annotations

import math

import torch
from mlagents_envs.base_env import ObservationSpec
from torch import nn

from learners.acting.numpy_policy import NORM_CLIP, encoder_width, is_entities
from learners.networks.encoders import visual_encoder
from learners.trainer_config.settings import NetworkSettings

NORM_CHUNK = 2**24  # numbers per float64 chunk of a normalization update (128 MB)


class RunningNorm(nn.Module):
    """Running mean and variance of a vector observation, kept in buffers.

    Buffers travel with the state_dict, so workers, checkpoints and the ONNX export all
    see the statistics the learner last updated (ML-Agents normalizes the same way).
    Only the learner calls ``update``; acting only reads.
    """

    def __init__(self, size: int, clip: float = NORM_CLIP) -> None:
        super().__init__()
        self.clip = clip
        self.register_buffer("count", torch.tensor(1e-4, dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(size))
        self.register_buffer("var", torch.ones(size))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.mean) * torch.rsqrt(self.var + 1e-8)).clamp(-self.clip, self.clip)

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merge a batch ``[..., size]`` into the statistics (parallel Welford), in float64
        chunks of at most ``NORM_CHUNK`` numbers, so a large batch is never copied whole."""
        x = x.reshape(-1, self.mean.shape[0])
        rows = max(1, NORM_CHUNK // self.mean.shape[0])
        for start in range(0, len(x), rows):
            self._merge(x[start : start + rows].to(torch.float64))

    def _merge(self, x: torch.Tensor) -> None:
        n, mean, var = float(len(x)), x.mean(0), x.var(0, unbiased=False)
        count = float(self.count)
        total = count + n
        delta = mean - self.mean.double()
        new_mean = self.mean.double() + delta * n / total
        m2 = self.var.double() * count + var * n + delta.square() * count * n / total
        self.mean.copy_(new_mean.float())
        self.var.copy_((m2 / total).float())
        self.count.fill_(total)


class SensorEncoder(nn.Module):
    """Vectors pass through flattened (normalized when ``normalize``); images ``[C, H, W]``
    (float in [0, 1] or uint8) go through ``settings.vis_encode_type``'s encoder to
    ``hidden_units`` features. ``sensor`` names the image in a too-small error. A
    variable-length sensor's rows (``entities``) are left to ``learners.networks.entities``
    (width 0 here, never normalized, as ML-Agents' entity embeddings)."""

    def __init__(
        self,
        shape: tuple[int, ...],
        settings: NetworkSettings,
        normalize: bool = False,
        sensor: str = "image",
        entities: bool = False,
    ) -> None:
        super().__init__()
        self.norm: RunningNorm | None = None
        self.image = len(shape) == 3
        self.entities = entities
        if entities:
            self.net: nn.Module = nn.Identity()
            self.size = 0
            return
        if self.image:
            self.net = visual_encoder(
                tuple(shape), settings.vis_encode_type, settings.hidden_units, sensor
            )
        else:
            self.net = nn.Flatten(start_dim=-len(shape)) if len(shape) > 1 else nn.Identity()
            if normalize:
                self.norm = RunningNorm(math.prod(shape))
        self.size = encoder_width(tuple(shape), settings)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.norm is not None:
            return self.norm(self.net(x))
        return self.net(x)

    @classmethod
    def of(
        cls, observation: ObservationSpec, settings: NetworkSettings, normalize: bool = False
    ) -> SensorEncoder:
        """The encoder of one sensor of a behavior spec."""
        shape = tuple(observation.shape)
        return cls(shape, settings, normalize, observation.name, is_entities(observation))
