"""POCA's centralized critic: one network, attending over however many agents a group has.

As ML-Agents' ``MultiAgentNetworkBody`` and ``POCAValueNetwork`` build it:

- each agent is an *entity*: its observations through this critic's own sensor encoders
  (normalized like the policy's), embedded by one linear layer with Swish; an entity that
  also carries its action (the action one-hot for discrete branches) has an embedding of
  its own;
- a residual self-attention block (layer norm, 4-head attention, an output layer, the
  residual, layer norm) and a mean over the present entities;
- ``num_layers`` Swish layers, then the value head, whose input also holds the number of
  present agents, scaled to [-1, 1] by the most ever seen (a buffer, so it travels with
  checkpoints).

``value``: every member by its observation alone, the group's value. ``baseline``: the
agent by its observation, each groupmate by observation and action: the counterfactual
baseline that marginalizes the agent's own action. Absent places (``present`` False)
are masked out of the attention and the mean. With the learner's mixed precision all but
the value head run in bfloat16 autocast.
"""

from __future__ import annotations

import contextlib
import math

import torch
from mlagents_envs.base_env import BehaviorSpec
from torch import nn

from learners.networks.entities import SelfAttention, entity_attention
from learners.networks.initializers import kaiming, normal
from learners.networks.mixed_precision import Autocast
from learners.networks.sensors import SensorEncoder
from learners.trainer_config.settings import NetworkSettings


class GroupCritic(nn.Module):
    def __init__(self, spec: BehaviorSpec, settings: NetworkSettings) -> None:
        super().__init__()
        h = settings.hidden_units
        self.sensor_names = [o.name for o in spec.observation_specs]
        self.encoders = nn.ModuleList(
            SensorEncoder.of(o, settings, settings.normalize) for o in spec.observation_specs
        )
        width = sum(e.size for e in self.encoders)
        self.entities = entity_attention(spec.observation_specs, width)  # a BufferSensor's
        width += self.entities.width if self.entities else 0
        self.branches = tuple(spec.action_spec.discrete_branches)
        actions = spec.action_spec.continuous_size + sum(self.branches)
        gain = math.sqrt(0.125 / h)
        self.obs_embedding = nn.Sequential(normal(width, h, gain), nn.SiLU())
        self.obs_action_embedding = nn.Sequential(normal(width + actions, h, gain), nn.SiLU())
        self.attention = SelfAttention(h)
        layers: list[nn.Module] = []
        for _ in range(settings.num_layers):
            layers += [kaiming(h, h, gain), nn.SiLU()]
        self.trunk = nn.Sequential(*layers)
        self.value_head = nn.Linear(h + 1, 1)
        nn.init.xavier_uniform_(self.value_head.weight)
        nn.init.zeros_(self.value_head.bias)
        self.register_buffer("most_agents", torch.tensor(1.0))
        # the learner's mixed precision (``learners.networks.mixed_precision``): all but the head in
        # bfloat16
        self.autocast: Autocast = contextlib.nullcontext

    def update_normalization(self, obs: dict[str, torch.Tensor]) -> None:
        """Fold the agents' own observations into this critic's running statistics."""
        for name, encoder in zip(self.sensor_names, self.encoders, strict=True):
            if encoder.norm is not None:
                encoder.norm.update(encoder.net(obs[name]))

    def encode(self, obs: dict[str, torch.Tensor], lead: int) -> torch.Tensor:
        """Sensor encodings of observations with ``lead`` batch dimensions."""
        parts, rows = [], []
        for name, encoder in zip(self.sensor_names, self.encoders, strict=True):
            x = obs[name]
            x = x.reshape(-1, *x.shape[lead:])  # also for no groupmates
            if encoder.entities:
                rows.append(x)
            else:
                parts.append(encoder(x))
        if self.entities is not None:
            parts.append(self.entities(list(parts), rows))
        encoded = torch.cat(parts, dim=-1)
        return encoded.reshape(*obs[self.sensor_names[0]].shape[:lead], encoded.shape[-1])

    def flat_action(
        self, continuous: torch.Tensor | None, discrete: torch.Tensor | None
    ) -> torch.Tensor:
        """Continuous actions, then a one-hot per discrete branch."""
        parts = [] if continuous is None else [continuous]
        for index, size in enumerate(self.branches):
            assert discrete is not None
            parts.append(nn.functional.one_hot(discrete[..., index], size).float())
        return torch.cat(parts, dim=-1)

    def value(
        self,
        obs: dict[str, torch.Tensor],
        mates: dict[str, torch.Tensor],
        present: torch.Tensor,
    ) -> torch.Tensor:
        """V of the group: the agent ``obs [B, ...]`` and its groupmates ``[B, M, ...]``."""
        with self.autocast():
            own = self.obs_embedding(self.encode(obs, 1)).unsqueeze(1)
            others = self.obs_embedding(self.encode(mates, 2))
        return self._head(torch.cat([own, others], 1), present)

    def baseline(
        self,
        obs: dict[str, torch.Tensor],
        mates: dict[str, torch.Tensor],
        mate_action: torch.Tensor,
        present: torch.Tensor,
    ) -> torch.Tensor:
        """The agent's counterfactual baseline: its observation without its action, and
        the groupmates with theirs (``mate_action``: ``flat_action``, ``[B, M, A]``)."""
        with self.autocast():
            own = self.obs_embedding(self.encode(obs, 1)).unsqueeze(1)
            mates_in = torch.cat([self.encode(mates, 2), mate_action], -1)
            others = self.obs_action_embedding(mates_in)
        return self._head(torch.cat([own, others], 1), present)

    def _head(self, entities: torch.Tensor, mates_present: torch.Tensor) -> torch.Tensor:
        own = mates_present.new_ones(len(mates_present), 1)
        present = torch.cat([own, mates_present], 1)
        count = present.float().sum(1, keepdim=True)
        with torch.no_grad():
            self.most_agents.copy_(torch.maximum(self.most_agents, count.max()))
        scaled = count * 2.0 / self.most_agents - 1
        with self.autocast():
            encoded = self.trunk(self.attention(entities, present))
        return self.value_head(torch.cat([encoded.float(), scaled], -1)).squeeze(-1)
