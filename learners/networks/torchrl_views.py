"""torchrl views of an :class:`~learners.networks.policies.ActorCritic`: the probabilistic actor and
the value operator that torchrl's losses (ClipPPOLoss, A2CLoss) and value estimators (GAE,
V-trace) take.

An ML-Agents action can be hybrid (continuous and several masked discrete branches at
once), so the actor's distribution is one :class:`ActionDistribution` over a flat action
vector ``[continuous..., branch indices as floats...]`` (key ``keys.FLAT_ACTION``), built
by :func:`add_flat_action` from the segment's ``("action", ...)`` entries. The modules
share the network's parameters; nothing here owns weights.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import (
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
)
from torch import nn
from torch.distributions import Distribution, Normal
from torchrl.modules import MaskedCategorical

from batches import keys
from learners.networks.policies import ActorCritic

FLAT_ACTION = "flat_action"
PARAM_KEYS = ("loc", "scale", "logits")


class ActionDistribution(Distribution):
    """Independent Gaussian (continuous) and masked categoricals (one per branch)."""

    arg_constraints: dict = {}
    has_rsample = False

    def __init__(
        self,
        loc: torch.Tensor | None = None,
        scale: torch.Tensor | None = None,
        logits: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        *,
        continuous: int = 0,
        branches: tuple[int, ...] = (),
    ) -> None:
        self.continuous, self.branches = continuous, branches
        self.normal = Normal(loc, scale, validate_args=False) if continuous else None
        self.categoricals: list[Distribution] = []
        if branches:
            assert logits is not None
            split_logits = torch.split(logits, branches, dim=-1)
            split_masks = (
                torch.split(mask, branches, dim=-1) if mask is not None else [None] * len(branches)
            )
            self.categoricals = [
                MaskedCategorical(logits=lg, mask=m) if m is not None else _categorical(lg)
                for lg, m in zip(split_logits, split_masks, strict=True)
            ]
        reference = loc if loc is not None else logits
        assert reference is not None
        super().__init__(batch_shape=reference.shape[:-1], validate_args=False)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        return self.log_prob_parts(value).sum(-1)

    def log_prob_parts(self, value: torch.Tensor) -> torch.Tensor:
        """One log-probability per action component ``[..., continuous + branches]``:
        each continuous dimension, then each branch (their sum is ``log_prob``)."""
        parts = []
        if self.normal is not None:
            parts.append(self.normal.log_prob(value[..., : self.continuous]))
        for index, dist in enumerate(self.categoricals):
            parts.append(dist.log_prob(value[..., self.continuous + index].long()).unsqueeze(-1))
        return torch.cat(parts, dim=-1)

    def entropy(self) -> torch.Tensor:
        """ML-Agents' measure, which ``beta`` weighs: the Gaussian's mean entropy per
        dimension, plus each branch's entropy."""
        reference = self.normal.loc if self.normal is not None else self.categoricals[0].logits
        total = torch.zeros(self.batch_shape, device=reference.device)
        if self.normal is not None:
            total = total + self.normal.entropy().mean(-1)
        for dist in self.categoricals:
            total = total + dist.entropy()
        return total

    def sample(self, sample_shape: torch.Size = torch.Size()) -> torch.Tensor:  # noqa: B008
        parts = [self.normal.sample(sample_shape)] if self.normal is not None else []
        parts += [d.sample(sample_shape).unsqueeze(-1).float() for d in self.categoricals]
        return torch.cat(parts, dim=-1)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        parts = [self.normal.mean] if self.normal is not None else []
        parts += [d.probs.argmax(-1, keepdim=True).float() for d in self.categoricals]
        return torch.cat(parts, dim=-1)


class TensorModule(TensorDictModule):
    """A ``TensorDictModule`` over a module that returns plain tensors, which it writes
    straight into the tensordict. The base class converts each output with tensordict's
    generic ``from_any``, which looks for pandas on every call (``importlib.util.
    find_spec``, 0.15 ms): a millisecond of each SAC gradient step went there."""

    def _write_to_tensordict(
        self,
        tensordict: TensorDictBase,
        tensors: list[torch.Tensor],
        tensordict_out: TensorDictBase | None = None,
        out_keys: Iterable[NestedKey] | None = None,
    ) -> TensorDictBase:
        plain = all(isinstance(t, torch.Tensor) for t in tensors)
        if tensordict_out is not None or self.inplace is not True or not plain:
            return super()._write_to_tensordict(tensordict, tensors, tensordict_out, out_keys)
        for key, tensor in zip(list(out_keys or self.out_keys_source), tensors, strict=True):
            if key != "_":
                tensordict.set(key, tensor)
        return tensordict


def _categorical(logits: torch.Tensor) -> Distribution:
    return torch.distributions.Categorical(logits=logits, validate_args=False)


class PolicyParams(nn.Module):
    """Observations (one tensor per sensor, in the network's order) -> distribution params."""

    def __init__(self, network: ActorCritic) -> None:
        super().__init__()
        self.network = network

    def forward(self, *sensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        net = self.network
        return self.heads(net.features(dict(zip(net.sensor_names, sensors, strict=True))))

    def heads(self, hidden: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The params from the actor's features (its trunk's, or its LSTM's output)."""
        net = self.network
        out: tuple[torch.Tensor, ...] = ()
        if net.mean is not None:
            loc, log_std = net.mean_log_std(hidden)
            out += (loc, log_std.exp())
        if net.logits is not None:
            out += (net.logits(hidden),)
        return out


class _StateValue(nn.Module):
    def __init__(self, network: ActorCritic) -> None:
        super().__init__()
        self.network = network

    def forward(self, *sensors: torch.Tensor) -> torch.Tensor:
        net = self.network
        return net.state_value(dict(zip(net.sensor_names, sensors, strict=True))).unsqueeze(-1)


def obs_keys(network: ActorCritic) -> list[tuple[str, str]]:
    return [(keys.OBS, name) for name in network.sensor_names]


def probabilistic_actor(network: ActorCritic) -> ProbabilisticTensorDictSequential:
    """The policy as torchrl losses want it: ``get_dist(td)`` over ``FLAT_ACTION``."""
    out_keys = (["loc", "scale"] if network.continuous else []) + (
        ["logits"] if network.branches else []
    )
    dist_keys = {key: key for key in out_keys}
    if network.branches:
        dist_keys["mask"] = keys.ACTION_MASK
    return ProbabilisticTensorDictSequential(
        TensorModule(PolicyParams(network), in_keys=obs_keys(network), out_keys=out_keys),
        ProbabilisticTensorDictModule(
            in_keys=dist_keys,
            out_keys=[FLAT_ACTION],
            distribution_class=ActionDistribution,
            distribution_kwargs={"continuous": network.continuous, "branches": network.branches},
            return_log_prob=False,
        ),
    )


def value_operator(network: ActorCritic) -> TensorDictModule:
    return TensorModule(_StateValue(network), in_keys=obs_keys(network), out_keys=["state_value"])


def add_flat_action(batch: TensorDictBase) -> TensorDictBase:
    """Join ``("action", "continuous")`` and ``("action", "discrete")`` into FLAT_ACTION."""
    parts = []
    if (keys.ACTION, keys.CONTINUOUS) in batch.keys(True):
        parts.append(batch[keys.ACTION, keys.CONTINUOUS])
    if (keys.ACTION, keys.DISCRETE) in batch.keys(True):
        parts.append(batch[keys.ACTION, keys.DISCRETE].float())
    batch.set(FLAT_ACTION, torch.cat(parts, dim=-1))
    return batch
