"""Attention over entities: a ``BufferSensor``'s rows, or the agents of a POCA group.

A variable-length observation (``DimensionProperty.VARIABLE_SIZE``, shape ``[max entities,
entity size]``, the absent rows all zeros, as Unity pads them) goes the way mlagents-learn's
``ObservationEncoder`` takes it:

- the agent's other encoded sensors ("self") through one Normal-initialised Swish layer to
  128 features (ML-Agents' ``ATTENTION_EMBEDDING_SIZE``, whatever ``hidden_units`` is);
- each entity, with that self encoding before its own features, through an embedding of its
  sensor (one Normal-initialised Swish layer to 128);
- the embeddings of every variable-length sensor side by side, through a residual
  self-attention block (:class:`SelfAttention`), masked where a row is absent (its squares
  sum below 0.01) and pooled by a masked mean;
- the pooled 128 appended after the other sensors' encodings (raw or normalized, not the
  self encoding, which feeds the embeddings only).

The actor-critic, SAC's Q networks and POCA's group critic each build one beside their sensor
encoders; the actor-critic's initial weights are drawn in numpy with the rest
(``learners.acting.numpy_policy.initial_entity_weights``), the others draw their own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from mlagents_envs.base_env import ObservationSpec
from torch import nn

from learners.acting.numpy_policy import ABSENT_BELOW, ATTENTION_WIDTH, ENTITY_GAIN, is_entities
from learners.networks.initializers import normal

HEADS = 4
NEG_INF = -1e6  # ML-Agents' additive mask for absent keys
POOL_EPS = 1e-7  # ML-Agents' epsilon in the masked mean


class SelfAttention(nn.Module):
    """Residual multi-head self-attention over entities, pooled by a masked mean: layer
    norm, 4-head attention, an output layer, the residual, layer norm (no affine terms)."""

    def __init__(self, width: int) -> None:
        super().__init__()
        gain = math.sqrt(ENTITY_GAIN / width)
        self.q, self.k, self.v, self.out = (normal(width, width, gain) for _ in range(4))
        self.width = width

    def forward(self, entities: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """``entities [B, E, W]``, ``present [B, E]`` bool -> ``[B, W]``. Shapes come from
        the module, not the input, so the ONNX export keeps a dynamic batch."""
        w = self.width
        x = nn.functional.layer_norm(entities, (w,))
        d = w // HEADS

        def heads(t: torch.Tensor) -> torch.Tensor:  # [B, E, W] -> [H, B, E, W/H]
            return torch.stack(t.split(d, dim=-1))

        q, k, v = heads(self.q(x)), heads(self.k(x)), heads(self.v(x))
        scores = q @ k.transpose(-1, -2) / math.sqrt(w)
        absent = (~present).to(scores.dtype).unsqueeze(1)  # [B, 1, E]: absent keys
        scores = (1 - absent) * scores + absent * NEG_INF
        attended = torch.cat(list(torch.softmax(scores, -1) @ v), dim=-1)  # [B, E, W]
        y = nn.functional.layer_norm(self.out(attended) + x, (w,))
        weight = present.to(y.dtype).unsqueeze(-1)
        return (y * weight).sum(1) / (weight.sum(1) + POOL_EPS)


def present_rows(entities: torch.Tensor) -> torch.Tensor:
    """``[B, E, S] -> [B, E]`` bool: the rows Unity filled (its padding is all zeros)."""
    return entities.square().sum(-1) >= ABSENT_BELOW


class EntityAttention(nn.Module):
    """The pooled attention over every variable-length sensor of a behavior."""

    def __init__(
        self, observations: Sequence[ObservationSpec], own_width: int, width: int = ATTENTION_WIDTH
    ) -> None:
        """``observations``: the behavior's sensors (the variable-length ones are read);
        ``own_width``: the other sensors' encoded width (0: none)."""
        super().__init__()
        gain = math.sqrt(ENTITY_GAIN / width)
        self.sensors = [i for i, o in enumerate(observations) if is_entities(o)]
        self.own = nn.Sequential(normal(own_width, width, gain), nn.SiLU()) if own_width else None
        before = width if own_width else 0
        self.embeddings = nn.ModuleList(
            nn.Sequential(normal(before + observations[i].shape[1], width, gain), nn.SiLU())
            for i in self.sensors
        )
        self.attention = SelfAttention(width)
        self.width = width

    def forward(
        self, own: Sequence[torch.Tensor], entities: Sequence[torch.Tensor]
    ) -> torch.Tensor:
        """``own``: the other sensors' encodings ``[B, *]``; ``entities``: each
        variable-length sensor's rows ``[B, E_i, S_i]`` in sensor order -> ``[B, width]``."""
        present = torch.cat([present_rows(e) for e in entities], dim=1)
        self_encoded = self.own(torch.cat(list(own), dim=-1)) if self.own is not None else None
        embedded = []
        for embedding, rows in zip(self.embeddings, entities, strict=True):
            if self_encoded is not None:
                beside = self_encoded.unsqueeze(1).expand(-1, rows.shape[1], -1)
                rows = torch.cat([beside, rows], dim=-1)
            embedded.append(embedding(rows))
        return self.attention(torch.cat(embedded, dim=1), present)


def entity_attention(
    observations: Sequence[ObservationSpec], own_width: int
) -> EntityAttention | None:
    """The attention a behavior's sensors need (None without a variable-length one)."""
    if not any(is_entities(o) for o in observations):
        return None
    return EntityAttention(observations, own_width)
