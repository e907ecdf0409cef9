"""SAC's Q networks: each with its own encoders and body, as ML-Agents gives each Q network
its own; with memory, an LSTM between the body and the output, as ML-Agents' Q networks
have (``learners/algorithms/recurrent_sac.py`` runs them over sequences, from zero memory)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from learners.networks.entities import entity_attention
from learners.networks.sensors import SensorEncoder

if TYPE_CHECKING:
    from learners.networks.policies import ActorCritic


class QNetwork(nn.Module):
    """Q(obs, continuous action) -> [1] (continuous) or [actions of every branch]
    (discrete; hybrid: given the continuous action).

    Own encoders (the policy's ``vis_encode_type`` per image sensor, as ML-Agents gives
    each Q network its own body) over observations normalized with the policy's running
    statistics, read but never trained here; then a SiLU MLP of the behavior's hidden
    units and layers.
    """

    def __init__(self, network: ActorCritic, outputs: int, action_size: int = 0) -> None:
        super().__init__()
        self.norms = [e.norm for e in network.encoders]  # a list: not submodules/params
        observations = network.spec.observation_specs
        self.encoders = nn.ModuleList(SensorEncoder.of(o, network.settings) for o in observations)
        own = sum(e.size for e in self.encoders)
        self.entities = entity_attention(observations, own)
        width = own + (self.entities.width if self.entities else 0) + action_size
        layers: list[nn.Module] = []
        for _ in range(network.settings.num_layers):
            layers += [nn.Linear(width, network.settings.hidden_units), nn.SiLU()]
            width = network.settings.hidden_units
        self.body = nn.Sequential(*layers, nn.Linear(width, outputs))
        self.width = width  # the features before the output layer

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.body[-1](self.trunk(*inputs))

    def trunk(self, *inputs: torch.Tensor) -> torch.Tensor:
        """The body's features before its output layer (the recurrent Q runs its LSTM here)."""
        parts, rows = [], []
        for encoder, norm, x in zip(self.encoders, self.norms, inputs, strict=False):
            if encoder.entities:
                rows.append(x)
                continue
            x = encoder(x)
            parts.append(norm(x) if norm is not None else x)
        if self.entities is not None:
            parts.append(self.entities(list(parts), rows))
        parts += inputs[len(self.encoders) :]  # the action, for continuous Q
        return self.body[:-1](torch.cat(parts, dim=-1))


class RecurrentQNetwork(QNetwork):
    """A ``QNetwork`` with an LSTM of ``memory_size / 2`` units before its output layer;
    ``sequences`` runs it over ``[B, L, ...]`` inputs from zero memory."""

    def __init__(self, network: ActorCritic, outputs: int, action_size: int = 0) -> None:
        super().__init__(network, outputs, action_size)
        memory = network.settings.memory
        assert memory is not None
        self.lstm = nn.LSTM(self.width, memory.memory_size // 2, batch_first=True)
        self.body[-1] = nn.Linear(memory.memory_size // 2, outputs)
        with torch.no_grad():  # ML-Agents' LSTM: Xavier per gate, zero biases, forget gate 1
            for weight in (self.lstm.weight_ih_l0, self.lstm.weight_hh_l0):
                for gate in weight.chunk(4):
                    nn.init.xavier_uniform_(gate)
            self.lstm.bias_ih_l0.zero_()
            self.lstm.bias_hh_l0.zero_()
            self.lstm.bias_ih_l0.chunk(4)[1].fill_(1.0)

    def sequences(self, *inputs: torch.Tensor) -> torch.Tensor:
        b, length = inputs[0].shape[:2]
        features = self.trunk(*(x.flatten(0, 1) for x in inputs)).unflatten(0, (b, length))
        return self.body[-1](self.lstm(features)[0])
