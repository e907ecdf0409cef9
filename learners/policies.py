"""Actor-critic networks built from an ML-Agents ``BehaviorSpec``.

One encoder per sensor (an MLP input for vectors, a small CNN for images and grids),
concatenated into a shared MLP trunk; heads for continuous actions (a Gaussian whose raw
sample is stored and clipped to [-1, 1] only when sent to Unity, as ML-Agents does), for
each discrete branch (a masked categorical: masked actions have probability zero), and
for the value. Plain torch: no Ray, so the learner side is testable in-process; the
rollout workers get a CPU copy through ``actor_factory``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from mlagents_envs.base_env import BehaviorSpec
from torch import nn
from torch.distributions import Normal
from torchrl.modules import MaskedCategorical


@dataclass(frozen=True)
class NetworkSettings:
    """ML-Agents ``network_settings``: hidden units and layers of the shared trunk."""

    hidden_units: int = 128
    num_layers: int = 2


class SensorEncoder(nn.Module):
    """Vectors pass through flattened; images ``[C, H, W]`` go through a small CNN."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        super().__init__()
        if len(shape) == 3:
            channels, height, width = shape
            self.net: nn.Module = nn.Sequential(
                nn.Conv2d(channels, 16, kernel_size=3, stride=2, padding=1),
                nn.ReLU(),
                nn.Conv2d(16, 32, kernel_size=3, stride=2, padding=1),
                nn.ReLU(),
                nn.Flatten(),
            )
            with torch.no_grad():
                self.size = int(self.net(torch.zeros(1, channels, height, width)).shape[1])
        else:
            self.net = nn.Flatten(start_dim=-len(shape)) if len(shape) > 1 else nn.Identity()
            self.size = math.prod(shape)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() > 4:  # [B, T, C, H, W]: fold the time axis for the convolutions
            lead = x.shape[:-3]
            return self.net(x.reshape(-1, *x.shape[-3:])).reshape(*lead, -1)
        return self.net(x)


class ActorCritic(nn.Module):
    def __init__(self, spec: BehaviorSpec, settings: NetworkSettings | None = None) -> None:
        super().__init__()
        settings = settings or NetworkSettings()
        self.sensor_names = [o.name for o in spec.observation_specs]
        self.encoders = nn.ModuleList(SensorEncoder(o.shape) for o in spec.observation_specs)
        width = sum(e.size for e in self.encoders)
        layers: list[nn.Module] = []
        for _ in range(settings.num_layers):
            layers += [nn.Linear(width, settings.hidden_units), nn.Tanh()]
            width = settings.hidden_units
        self.trunk = nn.Sequential(*layers)
        self.continuous = spec.action_spec.continuous_size
        self.branches = tuple(spec.action_spec.discrete_branches)
        self.mean = nn.Linear(width, self.continuous) if self.continuous else None
        self.log_std = nn.Parameter(torch.zeros(self.continuous)) if self.continuous else None
        self.logits = nn.Linear(width, sum(self.branches)) if self.branches else None
        self.value = nn.Linear(width, 1)

    def features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        parts = [enc(obs[name]) for name, enc in zip(self.sensor_names, self.encoders, strict=True)]
        return self.trunk(torch.cat(parts, dim=-1))

    def distributions(
        self, hidden: torch.Tensor, mask: torch.Tensor | None
    ) -> tuple[Normal | None, list[MaskedCategorical]]:
        normal = None
        if self.mean is not None and self.log_std is not None:
            normal = Normal(self.mean(hidden), self.log_std.exp().expand(self.continuous))
        branches = []
        if self.logits is not None:
            logits = torch.split(self.logits(hidden), self.branches, dim=-1)
            masks = (
                torch.split(mask, self.branches, dim=-1)
                if mask is not None
                else [None] * len(self.branches)
            )
            branches = [
                MaskedCategorical(logits=lg, mask=m) for lg, m in zip(logits, masks, strict=True)
            ]
        return normal, branches

    @torch.no_grad()
    def act(
        self,
        obs: dict[str, torch.Tensor],
        mask: torch.Tensor | None = None,
        deterministic: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(continuous [n, c], discrete [n, branches] int64, log-prob [n]) for a batch."""
        hidden = self.features(obs)
        normal, branches = self.distributions(hidden, mask)
        n = hidden.shape[0]
        log_prob = torch.zeros(n)
        continuous = torch.zeros(n, 0)
        if normal is not None:
            continuous = normal.mean if deterministic else normal.sample()
            log_prob = log_prob + normal.log_prob(continuous).sum(-1)
        discrete = torch.zeros(n, 0, dtype=torch.int64)
        if branches:
            picks = [(d.probs.argmax(-1) if deterministic else d.sample()) for d in branches]
            discrete = torch.stack(picks, dim=-1)
            log_prob = log_prob + sum(d.log_prob(p) for d, p in zip(branches, picks, strict=True))
        return continuous, discrete, log_prob

    def evaluate(
        self,
        obs: dict[str, torch.Tensor],
        continuous: torch.Tensor | None,
        discrete: torch.Tensor | None,
        mask: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(log-prob, entropy, value) of given actions; batch dims are kept."""
        hidden = self.features(obs)
        normal, branches = self.distributions(hidden, mask)
        lead = hidden.shape[:-1]
        log_prob, entropy = torch.zeros(lead), torch.zeros(lead)
        if normal is not None and continuous is not None:
            log_prob = log_prob + normal.log_prob(continuous).sum(-1)
            entropy = entropy + normal.entropy().sum(-1)
        for index, dist in enumerate(branches):
            assert discrete is not None
            log_prob = log_prob + dist.log_prob(discrete[..., index])
            entropy = entropy + dist.entropy()
        return log_prob, entropy, self.value(hidden).squeeze(-1)


def actor_factory(spec: BehaviorSpec) -> ActorCritic:
    """What rollout workers call to build their CPU copy of a behavior's policy."""
    return ActorCritic(spec)
