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
from torch.distributions import Categorical, Normal
from torchrl.modules import MaskedCategorical

_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


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
    ) -> tuple[Normal | None, list[Categorical]]:
        normal = None
        if self.mean is not None and self.log_std is not None:
            mean = self.mean(hidden)
            # validate_args=False: argument checks cost more than the tiny MLP per step
            normal = Normal(mean, self.log_std.exp().expand_as(mean), validate_args=False)
        return normal, self.branch_distributions(hidden, mask)

    def branch_distributions(
        self, hidden: torch.Tensor, mask: torch.Tensor | None
    ) -> list[Categorical]:
        """One categorical per discrete branch; masked actions (mask False) get probability 0."""
        if self.logits is None:
            return []
        logits = torch.split(self.logits(hidden), self.branches, dim=-1)
        if mask is None:
            return [Categorical(logits=lg, validate_args=False) for lg in logits]
        masks = torch.split(mask, self.branches, dim=-1)
        return [MaskedCategorical(logits=lg, mask=m) for lg, m in zip(logits, masks, strict=True)]

    @torch.no_grad()
    def act(
        self,
        obs: dict[str, torch.Tensor],
        mask: torch.Tensor | None = None,
        deterministic: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(continuous [n, c], discrete [n, branches] int64, log-prob [n]) for a batch."""
        hidden = self.features(obs)
        n = hidden.shape[0]
        log_prob = torch.zeros(n)
        continuous = torch.zeros(n, 0)
        if self.mean is not None and self.log_std is not None:
            # The Gaussian by hand: on the acting hot path, Distribution objects cost more
            # than the network (same values as Normal.sample / Normal.log_prob).
            mean, log_std = self.mean(hidden), self.log_std
            noise = torch.zeros_like(mean) if deterministic else torch.randn_like(mean)
            continuous = mean + noise * log_std.exp()
            log_prob = (-0.5 * noise.square() - log_std - _HALF_LOG_2PI).sum(-1)
        discrete = torch.zeros(n, 0, dtype=torch.int64)
        if self.logits is not None:
            # Gumbel-max sampling per branch over masked log-softmax logits: the same law
            # as MaskedCategorical.sample, without building distribution objects.
            logits = self.logits(hidden)
            if mask is not None:
                logits = logits.masked_fill(~mask, float("-inf"))
            picks, offset = [], 0
            for size in self.branches:
                branch_logp = torch.log_softmax(logits[:, offset : offset + size], dim=-1)
                offset += size
                scores = branch_logp
                if not deterministic:
                    scores = branch_logp - torch.empty_like(branch_logp).exponential_().log()
                pick = scores.argmax(-1)
                log_prob = log_prob + branch_logp.gather(-1, pick.unsqueeze(-1)).squeeze(-1)
                picks.append(pick)
            discrete = torch.stack(picks, dim=-1)
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
