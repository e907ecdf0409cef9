"""Actor-critic networks built from an ML-Agents ``BehaviorSpec``.

One encoder per sensor (``learners.networks.sensors``), concatenated into MLP trunks (policy and
value apart), each followed by an LSTM when ``network_settings.memory`` asks for one
(``memory_size // 2`` units; the memory is its hidden and cell state side by side, as
ML-Agents lays it out), with ML-Agents' layers: Swish activations and its
initializations, drawn in numpy by ``learners.acting.numpy_policy.initial_weights`` (trunk weights
``kaiming_normal`` for a linear layer, the Gaussian mean head at gain 0.2, discrete heads
at 0.1, the value head Xavier-uniform, log-std 0). Heads for continuous actions (a
Gaussian whose raw sample is stored; Unity receives ``clamp(a, -3, 3) / 3``, as from
mlagents-learn), for each discrete branch (a masked categorical: masked actions have
probability zero), and for the value.
Plain torch: no Ray, so the learner side is testable in-process. Rollout workers act
with ``learners.acting.numpy_policy`` (numpy, no torch) and come here only for images and goals
(``TorchActor``).

SAC networks (as ML-Agents builds them) set ``tanh_squash``: the action sent and stored is
``tanh(u)`` of the Gaussian sample ``u``, its log-probability carries the tanh Jacobian
correction; and ``conditional_sigma``: the log-std comes from a head on the trunk
(clamped to [LOG_STD_MIN, LOG_STD_MAX]) instead of a state-independent parameter.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from mlagents_envs.base_env import BehaviorSpec
from torch import nn

from learners.acting.numpy_policy import (
    ACTION_CLIP,
    LOG_STD_MAX,
    LOG_STD_MIN,
    goal_sensors,
    initial_weights,
    to_unity,
    trunk_input_width,
)
from learners.networks.entities import entity_attention
from learners.networks.mixed_precision import Autocast, AutocastLayers
from learners.networks.sensors import SensorEncoder
from learners.trainer_config.settings import NetworkSettings

_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)
_LOG_2 = math.log(2.0)
SQUASH_EPS = 1e-6  # stored squashed actions are clamped to +-(1 - eps) before atanh


def tanh_log_det(u: torch.Tensor) -> torch.Tensor:
    """log(1 - tanh(u)^2), stable for large |u| (the form torch's TanhTransform uses)."""
    return 2.0 * (_LOG_2 - u - torch.nn.functional.softplus(-2.0 * u))


def _mlp(width: int, settings: NetworkSettings) -> AutocastLayers:
    layers: list[nn.Module] = []
    for _ in range(settings.num_layers):
        layers += [nn.Linear(width, settings.hidden_units), nn.SiLU()]
        width = settings.hidden_units
    return AutocastLayers(*layers)


class ActorCritic(nn.Module):
    def __init__(
        self,
        spec: BehaviorSpec,
        settings: NetworkSettings | None = None,
        initial: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """``initial``: every weight (``acting.initial_weights``, ML-Agents' initialization),
        drawn here from a seed taken from torch's random stream when not given.
        An image below its encoder's minimum size raises ``encoders.ImageTooSmall``."""
        super().__init__()
        settings = settings or NetworkSettings()
        self.spec, self.settings = spec, settings
        self.sensor_names = [o.name for o in spec.observation_specs]
        self.encoders = nn.ModuleList(
            SensorEncoder.of(o, settings, settings.normalize) for o in spec.observation_specs
        )
        own = sum(e.size for e in self.encoders)
        # the actor's and the critic's own attention, as ML-Agents' separate critic has
        self.entities = entity_attention(spec.observation_specs, own)
        self.critic_entities = entity_attention(spec.observation_specs, own)
        self.goal_sensors = goal_sensors(spec, settings)
        encoded = trunk_input_width(spec, settings)
        # Separate policy and value trunks over shared encoders (ML-Agents' default,
        # shared_critic: false): the value loss does not pull on the policy's features.
        self.trunk = _mlp(encoded, settings)
        self.critic_trunk = _mlp(encoded, settings)
        width = settings.hidden_units if settings.num_layers else encoded
        # ML-Agents' memory: an LSTM after each trunk, memory_size // 2 units (hidden and
        # cell state side by side make the memory a worker carries per agent)
        self.lstm = self.critic_lstm = None
        if settings.memory is not None:
            units = settings.memory.memory_size // 2
            self.lstm = nn.LSTM(width, units, batch_first=True)
            self.critic_lstm = nn.LSTM(width, units, batch_first=True)
            width = units
        self.continuous = spec.action_spec.continuous_size
        self.branches = tuple(spec.action_spec.discrete_branches)
        self.mean = nn.Linear(width, self.continuous) if self.continuous else None
        conditional = bool(self.continuous) and settings.conditional_sigma
        self.log_std = (
            nn.Parameter(torch.zeros(self.continuous))
            if self.continuous and not conditional
            else None
        )
        self.log_std_head = nn.Linear(width, self.continuous) if conditional else None
        self.logits = nn.Linear(width, sum(self.branches)) if self.branches else None
        self.value = nn.Linear(width, 1)
        if initial is None:
            rng = np.random.default_rng(int(torch.randint(2**31 - 1, ())))
            initial = initial_weights(spec, settings, rng)
        self.load_state_dict({k: torch.from_numpy(v) for k, v in initial.items()})
        # the learner's mixed precision (``learners.networks.mixed_precision``): image encoders in
        # bfloat16
        self.autocast: Autocast = contextlib.nullcontext

    def update_normalization(
        self, obs: dict[str, torch.Tensor], rows: torch.Tensor | None = None
    ) -> None:
        """Fold observations the learner trains on (``rows`` of them, else all) into the
        running statistics; only normalized sensors are read."""
        for name, encoder in zip(self.sensor_names, self.encoders, strict=True):
            if encoder.norm is not None:
                values = obs[name] if rows is None else obs[name][rows]
                encoder.norm.update(encoder.net(values))

    def encode(self, obs: dict[str, torch.Tensor], critic: bool = False) -> torch.Tensor:
        """Each sensor's encoding in sensor order, then the entity attention's (the
        actor's, or with ``critic`` the critic's) over the variable-length sensors; goals
        condition the rest."""
        return self._joined(self._sensor_parts(obs), obs, critic)

    def encode_both(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The actor's and the critic's ``encode``, the sensors encoded once for both
        (images cost the most here); one tensor twice without a variable-length sensor."""
        parts = self._sensor_parts(obs)
        actor = self._joined(parts, obs, False)
        return actor, actor if self.critic_entities is None else self._joined(parts, obs, True)

    def _sensor_parts(self, obs: dict[str, torch.Tensor]) -> dict[int, torch.Tensor]:
        parts: dict[int, torch.Tensor] = {}
        for i, (name, encoder) in enumerate(zip(self.sensor_names, self.encoders, strict=True)):
            if encoder.entities:
                continue
            if encoder.image:  # where mixed precision pays
                with self.autocast():
                    parts[i] = encoder(obs[name]).float()
            else:
                parts[i] = encoder(obs[name])
        return parts

    def _joined(
        self, parts: dict[int, torch.Tensor], obs: dict[str, torch.Tensor], critic: bool
    ) -> torch.Tensor:
        other = [p for i, p in parts.items() if i not in self.goal_sensors]
        entities = self.critic_entities if critic else self.entities
        if entities is not None:
            rows = [obs[self.sensor_names[i]] for i in entities.sensors]
            other.append(entities(list(parts.values()), rows))
        if not self.goal_sensors:
            return torch.cat(other, dim=-1)
        goal = torch.cat([parts[i] for i in self.goal_sensors], dim=-1)
        conditioned = (torch.cat(other, dim=-1).unsqueeze(-1) * goal.unsqueeze(-2)).flatten(-2)
        return torch.cat([conditioned, goal], dim=-1)

    @property
    def memory_size(self) -> int:
        """The memory a worker carries per agent (0: none): the actor LSTM's state."""
        return 0 if self.lstm is None else 2 * self.lstm.hidden_size

    def features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.trunk(self.encode(obs))

    @staticmethod
    def recur(
        lstm: nn.LSTM, x: torch.Tensor, memory: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``lstm`` over ``x`` ``[B, L, H]`` (or one step, ``[B, H]``) from ``memory``
        ``[B, 2 * units]`` (hidden state, then cell state; None: zeros): the outputs and
        the memory after the last step."""
        step = x.dim() == 2
        if step:
            x = x.unsqueeze(1)
        units = lstm.hidden_size
        if memory is None:
            memory = x.new_zeros(x.shape[0], 2 * units)
        out, (h, c) = lstm(x, lstm_state(memory, units))
        return (out[:, 0] if step else out), torch.cat([h[0], c[0]], dim=-1)

    def sequence_features(
        self, obs: dict[str, torch.Tensor], memory: torch.Tensor, critic_memory: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Actor and critic features of sequences: ``obs`` ``[B, L, ...]``, each LSTM from
        its memory at the sequences' first steps ``[B, memory_size]``."""
        assert self.lstm is not None and self.critic_lstm is not None
        b, length = next(iter(obs.values())).shape[:2]
        encoded, critic_encoded = self.encode_both({n: o.flatten(0, 1) for n, o in obs.items()})
        actor = self.trunk(encoded).unflatten(0, (b, length))
        critic = self.critic_trunk(critic_encoded).unflatten(0, (b, length))
        return self.recur(self.lstm, actor, memory)[0], self.recur(
            self.critic_lstm, critic, critic_memory
        )[0]

    def state_value(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """V(obs) with the batch dims kept (no trailing 1)."""
        return self.value_of(self.encode(obs, critic=True))

    def value_of(self, encoded: torch.Tensor, heads: Sequence[nn.Module] = ()) -> torch.Tensor:
        """V from observations the critic encoded (``encode(obs, critic=True)``); with
        ``heads`` (an intrinsic signal's value head each, ``learners/reward_signals/
        intrinsic.py``) ``[..., 1 + H]``, the extrinsic value first."""
        critic = self.critic_trunk(encoded)
        return self.value_head(critic, heads)

    def value_head(self, critic: torch.Tensor, heads: Sequence[nn.Module] = ()) -> torch.Tensor:
        """V from the critic's features (its trunk's, or its LSTM's output)."""
        value = self.value(critic)
        if not heads:
            return value.squeeze(-1)
        return torch.cat([value, *(head(critic) for head in heads)], dim=-1)

    def unity_action(self, continuous: torch.Tensor) -> torch.Tensor:
        """The continuous action Unity receives for a stored one (squashed: as it is)."""
        if self.settings.tanh_squash:
            return continuous
        return continuous.clamp(-ACTION_CLIP, ACTION_CLIP) / ACTION_CLIP

    def mean_log_std(self, hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The Gaussian's mean and log-std (before any tanh squash) for a trunk output."""
        assert self.mean is not None
        mean = self.mean(hidden)
        if self.log_std_head is not None:
            return mean, self.log_std_head(hidden).clamp(LOG_STD_MIN, LOG_STD_MAX)
        assert self.log_std is not None
        return mean, self.log_std.expand_as(mean)

    @torch.no_grad()
    def act(
        self,
        obs: dict[str, torch.Tensor],
        mask: torch.Tensor | None = None,
        deterministic: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(continuous [n, c], discrete [n, branches] int64, log-probs [n, c + branches])
        for a batch: one log-probability per action component (``LOG_PROB``). With memory,
        from zeros; ``act_recurrent`` takes each agent's memory and gives the next."""
        return self.act_recurrent(obs, mask, None, deterministic)[:3]

    @torch.no_grad()
    def act_recurrent(
        self,
        obs: dict[str, torch.Tensor],
        mask: torch.Tensor | None,
        memory: torch.Tensor | None,
        deterministic: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        hidden, next_memory = self.features(obs), None
        if self.lstm is not None:
            hidden, next_memory = self.recur(self.lstm, hidden, memory)
        n = hidden.shape[0]
        log_probs = [torch.zeros(n, 0, device=hidden.device)]
        continuous = torch.zeros(n, 0, device=hidden.device)
        if self.mean is not None:
            # The Gaussian by hand: on the acting hot path, Distribution objects cost more
            # than the network (same values as Normal.sample / Normal.log_prob).
            mean, log_std = self.mean_log_std(hidden)
            noise = torch.zeros_like(mean) if deterministic else torch.randn_like(mean)
            continuous = mean + noise * log_std.exp()
            gaussian = -0.5 * noise.square() - log_std - _HALF_LOG_2PI
            if self.settings.tanh_squash:  # log p(tanh u) = log p(u) - log|d tanh/du|
                gaussian = gaussian - tanh_log_det(continuous)
                continuous = torch.tanh(continuous)
            log_probs.append(gaussian)
        discrete = torch.zeros(n, 0, dtype=torch.int64, device=hidden.device)
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
                log_probs.append(branch_logp.gather(-1, pick.unsqueeze(-1)))
                picks.append(pick)
            discrete = torch.stack(picks, dim=-1)
        return continuous, discrete, torch.cat(log_probs, dim=-1), next_memory

    def evaluate(
        self,
        obs: dict[str, torch.Tensor],
        continuous: torch.Tensor | None,
        discrete: torch.Tensor | None,
        mask: torch.Tensor | None = None,
        heads: Sequence[nn.Module] = (),
        memories: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(log-probs [..., c + branches] as ``act`` gives them, entropy, value) of given
        actions under the current weights (what PPO's loss needs); batch dims are kept.
        With memory: of sequences ``[B, L, ...]`` from ``memories`` (the actor's and the
        critic's at each sequence's start, ``[B, memory_size]`` each).
        The densities are written out (the Gaussian's, and each branch's masked softmax):
        building ``torch.distributions`` objects cost more than the network per minibatch."""
        if memories is not None:
            hidden, critic = self.sequence_features(obs, *memories)
        else:
            encoded, critic_encoded = self.encode_both(obs)
            hidden, critic = self.trunk(encoded), self.critic_trunk(critic_encoded)
        lead = hidden.shape[:-1]
        log_probs = [torch.zeros(*lead, 0, device=hidden.device)]
        entropy = torch.zeros(lead, device=hidden.device)
        if self.mean is not None and continuous is not None:
            mean, log_std = self.mean_log_std(hidden)
            u = continuous
            if self.settings.tanh_squash:  # invert the squash on the stored tanh(u)
                bound = 1.0 - SQUASH_EPS
                u = torch.atanh(continuous.clamp(-bound, bound))
            gaussian = -0.5 * ((u - mean) * torch.exp(-log_std)).square() - log_std - _HALF_LOG_2PI
            if self.settings.tanh_squash:
                gaussian = gaussian - tanh_log_det(u)
            log_probs.append(gaussian)
            # ML-Agents' measure, which beta weighs: the mean over dimensions (squashed:
            # the pre-squash Gaussian's, which has a closed form; ML-Agents does the same)
            entropy = entropy + (0.5 + _HALF_LOG_2PI + log_std).mean(-1)
        if self.logits is not None and discrete is not None:
            logits = self.logits(hidden)
            if mask is not None:  # masked actions: probability 0
                logits = logits.masked_fill(~mask, float("-inf"))
            offset = 0
            for index, size in enumerate(self.branches):
                branch = torch.log_softmax(logits[..., offset : offset + size], dim=-1)
                offset += size
                log_probs.append(branch.gather(-1, discrete[..., index : index + 1]))
                # masked entries add 0 (and no NaN gradient: 0 * -inf never happens)
                finite = torch.where(branch.isfinite(), branch, 0.0)
                entropy = entropy - (branch.exp() * finite).sum(-1)
        return torch.cat(log_probs, dim=-1), entropy, self.value_head(critic, heads)


class TorchActor:
    """A worker's actor for behaviors the numpy one does not cover (images, goal
    conditioning): the torch network, numpy in and out. Loads numpy or torch weights."""

    def __init__(self, network: ActorCritic) -> None:
        self.network = network

    def load_state_dict(self, state: Mapping[str, object]) -> None:
        self.network.load_state_dict({k: torch.as_tensor(v) for k, v in state.items()})

    def to_unity(self, continuous: np.ndarray) -> np.ndarray:
        return to_unity(continuous, self.network.settings)

    @property
    def memory_size(self) -> int:
        return self.network.memory_size

    def act(
        self, obs: dict[str, np.ndarray], mask: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.act_recurrent(obs, mask, None)[:3]

    def act_recurrent(
        self, obs: dict[str, np.ndarray], mask: np.ndarray | None, memory: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        tensors = {name: torch.from_numpy(value) for name, value in obs.items()}
        torch_mask = torch.from_numpy(mask) if mask is not None else None
        torch_memory = torch.from_numpy(memory) if memory is not None else None
        deterministic = self.network.settings.deterministic
        acted = self.network.act_recurrent(tensors, torch_mask, torch_memory, deterministic)
        return tuple(None if t is None else t.numpy() for t in acted)  # type: ignore[return-value]


def lstm_state(memory: torch.Tensor, units: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``nn.LSTM``'s (h0, c0) from memories ``[B, 2 * units]`` (hidden, then cell state)."""
    return (
        memory[:, :units].unsqueeze(0).contiguous(),
        memory[:, units:].unsqueeze(0).contiguous(),
    )


def seeded_network(
    spec: BehaviorSpec, settings: NetworkSettings, seed: int, initial: Mapping[str, np.ndarray]
) -> ActorCritic:
    """An ``ActorCritic`` with ``initial`` weights (``acting.initial_weights``); the draws
    torch's layers make when built (all replaced) come from a stream seeded by ``seed``,
    so the caller's random stream is left as it was."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return ActorCritic(spec, settings, initial)


def numpy_state(network: nn.Module) -> dict[str, np.ndarray]:
    """A network's weights as numpy copies: what workers load without torch."""
    return {k: v.detach().cpu().numpy().copy() for k, v in network.state_dict().items()}
