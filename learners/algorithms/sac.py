"""SAC for one behavior: continuous actions, masked discrete branches, or both (hybrid),
as ML-Agents' SAC trains them, with torchrl's ``TensorDictReplayBuffer`` and
``TanhNormal``; the losses written out in torch.

``add`` turns every step of a packed segment into a transition (obs, actions,
reward * strength, next obs, terminated, done; discrete: the masks of both states) in a
replay buffer of ``buffer_size`` steps. ``ready`` once it holds ``max(buffer_init_steps,
batch_size)`` steps and ``steps_per_update`` new ones came. ``update`` takes one gradient
step per ``steps_per_update`` new steps (at most ``MAX_GRADIENT_STEPS``), each on
``batch_size`` sampled transitions:

- twin Q regress to ``r + gamma (1 - terminated) V(s')``, where ``V(s')`` is
  ``min_i Q_target_i(s', a') - alpha log pi(a'|s')`` for a fresh ``a' ~ pi`` (discrete:
  the exact expectation over the masked softmax of ``min_i Q_target_i - alpha log pi``);
- the tanh-squashed policy minimizes ``alpha log pi(a|s) - min_i Q_i(s, a)`` for a
  reparameterized ``a`` (discrete: the expectation), with the Qs' weights held fixed;
- ``log alpha`` follows the "auto" target entropy (``-action dims``; discrete
  ``0.2 log(actions)``);
- then the target Qs move by ``tau`` (Polyak).

Curiosity, RND and GAIL as ML-Agents' SAC has them (``learners/reward_signals/sac_streams.py``): the
Qs have outputs per reward stream, each regressing to its reward with its own gamma; the policy
reads their mean.

With several branches, as ML-Agents: a Q network outputs one value per action of every
branch (given the continuous action, when there is one), ``Q(s, a)`` is the mean over
branches of each branch's value of its action, ``V`` the mean over branches of each
branch's expectation, the policy loss the sum over branches (plus the continuous part's),
and each branch has its own entropy coefficient and target (``log_alpha``: the continuous
part's first, then one per branch).

The math is torchrl's ``SACLoss`` / ``DiscreteSACLoss`` (v2, two Q networks, l2) written
out: a gradient step on 3DBall's network takes a third of the time (docs/benchmarks.md).
With ``network_settings.memory``, ``learners/algorithms/recurrent_sac.py`` runs it on sequences.

Off-policy: the policy lag ``add`` gets is ignored. The replay buffer is not in
``state_dict`` (a resumed run refills it before updating again).
"""

from __future__ import annotations

import copy
import math
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.modules import TanhNormal

from batches import keys
from learners.algorithms.sac_terms import (
    CONTINUOUS_ACTION,
    DISCRETE_ACTION,
    expected_value,
    log_probs,
    next_mask,
    split,
    taken,
)
from learners.algorithms.schedules import decay
from learners.host.devices import Compute
from learners.networks.policies import ActorCritic
from learners.networks.q_networks import QNetwork
from learners.networks.torchrl_views import PolicyParams
from learners.reward_signals.extrinsic import extrinsic_reward
from learners.reward_signals.ppo_streams import make_signals
from learners.reward_signals.sac_streams import SacSignals

if TYPE_CHECKING:
    from collections.abc import Mapping

    from batches.expert_steps import ExpertSteps
    from learners.trainer_config.settings import TrainerSettings

MAX_GRADIENT_STEPS = 200  # per update() call, so one call stays short; the rest is dropped
DISCRETE_TARGET_ENTROPY_SCALE = 0.2  # ML-Agents' discrete_target_entropy_scale


class SAC:
    q_network: type[QNetwork] = QNetwork

    def __init__(
        self,
        network: ActorCritic,
        settings: TrainerSettings,
        compute: Compute | None = None,
        experts: Mapping[str, ExpertSteps] | None = None,
    ) -> None:
        """``experts``: the demonstrations of a ``gail`` signal, by ``demo_path``."""
        self.compute = compute or Compute()
        self.branches = tuple(network.branches)
        if not (network.continuous or self.branches):
            raise ValueError("SAC needs actions: this behavior has none")
        self.network, self.settings = network, settings
        self.continuous = bool(network.continuous)
        h = settings.hyperparameters
        device = self.compute.torch_device
        self.policy = PolicyParams(network)  # (loc, scale) and/or (logits of every branch,)
        signals = make_signals(network, settings.reward_signals, device, experts)
        self.signals = SacSignals(network, signals)
        self.streams = 1 + len(self.signals)  # reward streams: the extrinsic, then the others
        outputs = (sum(self.branches) or 1) * self.streams
        self.q = nn.ModuleList(
            self.q_network(network, outputs, network.continuous) for _ in range(2)
        )
        self.q.to(device)
        self.q_target = copy.deepcopy(self.q).requires_grad_(False)
        for target, q in zip(self.q_target, self.q, strict=True):
            target.norms = q.norms  # the policy's running statistics, not frozen copies
        # one coefficient for the continuous part, one per branch: [parts]
        targets = ([-float(network.continuous)] if self.continuous else []) + [
            DISCRETE_TARGET_ENTROPY_SCALE * math.log(n) for n in self.branches
        ]
        self.target_entropy = torch.tensor(targets, device=device)
        self.log_alpha = torch.full(
            (len(targets),), math.log(h.init_entcoef), device=device, requires_grad=True
        )
        self.actor_optimizer = torch.optim.Adam(
            network.parameters(), lr=h.learning_rate, fused=True
        )
        self.critic_optimizer = torch.optim.Adam(
            self.q.parameters(), lr=h.learning_rate, fused=True
        )
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=h.learning_rate, fused=True)
        self.optimizers = (self.actor_optimizer, self.critic_optimizer, self.alpha_optimizer)
        self._q_params = list(self.q.parameters())
        self._q_target_params = list(self.q_target.parameters())
        # compilable: plain counters, not multiprocessing.Value (this buffer never leaves
        # the learner process, and mp.Value would start a resource-tracker process)
        self.buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(self.items(h.buffer_size), device=device, compilable=True),
            batch_size=self.items(h.batch_size),
            compilable=True,
        )
        self.tau = h.tau
        self.threshold = max(h.buffer_init_steps, h.batch_size)
        self.received = 0  # valid steps added, ever
        self.new_steps = 0.0  # steps past the threshold not yet paid in gradient steps
        self.signal_steps = 0.0  # the same, not yet paid in the signals' updates
        self.gradient_steps = 0
        self.dropped_gradient_steps = 0  # owed beyond MAX_GRADIENT_STEPS, not taken

    # --- data in ------------------------------------------------------------------------

    def add(self, segment: TensorDict, lag: torch.Tensor) -> int:
        """Every step of a packed segment into the replay buffer (``lag`` unused: replayed
        data is off-policy anyway); returns the steps added."""
        steps = segment.batch_size[0]
        if not steps:
            return 0
        nxt = segment[keys.NEXT]
        actions = {}
        if self.continuous:
            actions[CONTINUOUS_ACTION] = segment[keys.ACTION, keys.CONTINUOUS]
        if self.branches:
            actions[DISCRETE_ACTION] = segment[keys.ACTION, keys.DISCRETE].long()
        transitions = TensorDict(
            {
                keys.OBS: segment[keys.OBS],
                **actions,
                keys.NEXT: {
                    keys.OBS: nxt[keys.OBS],
                    keys.REWARD: extrinsic_reward(segment) * self.settings.reward_strength,
                    keys.DONE: nxt[keys.DONE],
                    keys.TERMINATED: nxt[keys.TERMINATED],
                },
            },
            batch_size=segment.batch_size,
        )
        if self.branches:
            mask = segment[keys.ACTION_MASK]
            transitions[keys.ACTION_MASK] = mask
            transitions[keys.NEXT, keys.ACTION_MASK] = next_mask(mask, nxt[keys.DONE])
        self.network.update_normalization(transitions[keys.OBS].to_dict())
        if self.signals:
            self.signals.update_normalization(transitions)
            self.signals.observe(transitions, segment)
        self.store(transitions, segment)
        before = self.received
        self.received += steps
        fresh = max(0, self.received - max(before, self.threshold))
        self.new_steps += fresh
        self.signal_steps += fresh
        return steps

    def items(self, steps: int) -> int:
        """Replay items for ``steps`` steps (a recurrent SAC's items are sequences)."""
        return steps

    def store(self, transitions: TensorDict, segment: TensorDict) -> None:
        self.buffer.extend(transitions)

    def stored_steps(self) -> int:
        return len(self.buffer)

    def ready(self) -> bool:
        h = self.settings.hyperparameters
        return self.stored_steps() >= self.threshold and self.new_steps >= h.steps_per_update

    def wanted(self) -> None:
        return None  # off-policy: any amount of data is welcome at any time

    # --- the update ---------------------------------------------------------------------

    def update(self, progress: float) -> dict[str, float]:
        """One gradient step per ``steps_per_update`` new steps (capped); ``progress`` in
        [0, 1] drives the learning-rate schedule."""
        h = self.settings.hyperparameters
        owed = int(self.new_steps / h.steps_per_update)
        self.new_steps -= owed * h.steps_per_update
        count = min(owed, MAX_GRADIENT_STEPS)
        self.dropped_gradient_steps += owed - count
        lr = decay(h.learning_rate, progress, h.learning_rate_schedule)
        for optimizer in self.optimizers:
            for group in optimizer.param_groups:
                group["lr"] = lr
        totals: dict[str, torch.Tensor] = {}
        last: dict[str, torch.Tensor] = {}
        for _ in range(count):
            last = self.gradient_step(self.buffer.sample())
            for key in ("policy", "alpha_loss", "entropy"):
                totals[key] = totals[key] + last[key] if key in totals else last[key]
        self.gradient_steps += count
        signals = self.train_signals()
        mean = {key: float(value) / max(count, 1) for key, value in totals.items()}
        # each Q's loss and estimate: of the last step only (one sync, not one per step)
        mean.update({key: float(last[key]) for key in ("q1", "q2", "estimate") if key in last})
        return {
            **signals,
            "Losses/Policy Loss": mean.get("policy", 0.0),
            "Losses/Q1 Loss": mean.get("q1", 0.0),
            "Losses/Q2 Loss": mean.get("q2", 0.0),
            "Losses/Entropy Coeff Loss": mean.get("alpha_loss", 0.0),
            "Policy/Entropy Coeff": float(self.log_alpha.detach().exp().mean()),
            "Policy/Entropy": mean.get("entropy", 0.0),
            "Policy/Learning Rate": lr,
            "Policy/Extrinsic Value Estimate": mean.get("estimate", 0.0),
            "Policy/Gradient Steps": float(count),
            "Policy/Dropped Gradient Steps": float(self.dropped_gradient_steps),
            "Policy/Samples": float(count * h.batch_size),
        }

    def train_signals(self) -> dict[str, float]:
        """One update of the signals' networks per ``reward_signal_steps_per_update`` new
        steps (capped as the gradient steps), each on a sampled batch; the mean losses."""
        if not self.signals:
            return {}
        h = self.settings.hyperparameters
        rate = h.reward_signal_steps_per_update or h.steps_per_update
        owed = int(self.signal_steps / rate)
        self.signal_steps -= owed * rate
        return self.signals.train(self.sample() for _ in range(min(owed, MAX_GRADIENT_STEPS)))

    def sample(self) -> TensorDict:
        """The transitions of one sampled item (what the signals train on)."""
        return self.steps(self.buffer.sample())

    def gradient_step(self, sampled: TensorDict) -> dict[str, torch.Tensor]:
        """One step of all three losses on a sampled batch (each computed with the
        weights before the step, summed, one backward), then the Polyak target update.
        Returns detached scalars: the losses, the entropy, each Q's squared TD error and
        the mean Q of the stored actions."""
        batch = self.steps(sampled)
        obs = self.inputs(sampled)
        alpha = self.log_alpha.detach().exp()
        target = self.target(sampled, alpha, batch)  # its draw of a' first, as torchrl's
        stored = [batch[CONTINUOUS_ACTION]] if self.continuous else []
        values = self.q_values(self.q, obs, stored)  # [2, B, streams, outputs]
        chosen = taken(values, batch.get(DISCRETE_ACTION, None), self.branches)  # [2, B, S]
        params = self.policy_params(obs)
        neg_entropy: list[torch.Tensor] = []  # per part: E[log pi], [B]
        policy_loss = torch.zeros((), device=alpha.device)
        if self.continuous:
            action, log_prob = self._sample(params[0], params[1])
            for param in self._q_params:  # the actor's gradient reaches the action only
                param.requires_grad_(False)
            policy_values = self.q_values(self.q, obs, [action]).min(0).values.mean(-2)
            for param in self._q_params:
                param.requires_grad_(True)
            policy_loss = (alpha[0] * log_prob).mean()
            neg_entropy.append(log_prob.detach())
            if not self.branches:
                policy_loss = policy_loss - policy_values.squeeze(-1).mean()
        else:
            policy_values = values.detach().min(0).values.mean(-2)  # [B, outputs]
        if self.branches:
            each = log_probs(params[-1], batch[keys.ACTION_MASK], self.branches)
            parts = zip(each, split(policy_values, self.branches), strict=True)
            for i, (log_prob, value) in enumerate(parts, start=int(self.continuous)):
                prob = log_prob.exp()
                policy_loss = policy_loss + (prob * (alpha[i] * log_prob - value)).sum(-1).mean()
                neg_entropy.append((prob * log_prob).sum(-1).detach())
        errors = (chosen - target).square().flatten(1).mean(-1)  # [2]: each Q's, all streams
        ent = torch.stack(neg_entropy, dim=-1)  # [B, parts]
        alpha_loss = -(self.log_alpha * (ent + self.target_entropy)).mean(0).sum()
        for optimizer in self.optimizers:
            optimizer.zero_grad()
        (policy_loss + errors.sum() + alpha_loss).backward()
        for optimizer in self.optimizers:
            optimizer.step()
        with torch.no_grad():
            torch._foreach_lerp_(self._q_target_params, self._q_params, self.tau)
        errors = errors.detach()
        return {
            "policy": policy_loss.detach(),
            "alpha_loss": alpha_loss.detach(),
            "entropy": -ent.sum(-1).mean(),
            "q1": errors[0],
            "q2": errors[1],
            "estimate": chosen.detach()[..., 0].mean(),
        }

    # what a sampled item holds, and the networks' passes over it
    # (learners/algorithms/recurrent_sac.py samples sequences and runs over them)

    def steps(self, sampled: TensorDict) -> TensorDict:
        """The transitions of a sampled item that the losses average over."""
        return sampled

    def inputs(self, sampled: TensorDict, after: bool = False) -> Any:
        """What ``policy_params`` and ``q_values`` read of a sampled item (``after``: of
        the states after its steps)."""
        source = sampled[keys.NEXT] if after else sampled
        return [source[keys.OBS, name] for name in self.network.sensor_names]

    def policy_params(self, inputs: Any) -> tuple[torch.Tensor, ...]:
        return self.policy(*inputs)

    def q_values(self, qs: nn.ModuleList, inputs: Any, actions: list[torch.Tensor]) -> torch.Tensor:
        """Both Qs' outputs ``[2, B, streams, outputs]`` (continuous: of ``actions``)."""
        return torch.stack([q(*inputs, *actions) for q in qs]).unflatten(-1, (self.streams, -1))

    @torch.no_grad()
    def target(
        self, sampled: TensorDict, alpha: torch.Tensor, batch: TensorDict | None = None
    ) -> torch.Tensor:
        """``r + gamma (1 - terminated) V(s')`` with the target Qs: ``V`` of a fresh
        ``a' ~ pi(s')`` (continuous), the expectation over each branch's masked softmax
        (discrete: their mean over branches), both for hybrid actions."""
        batch = self.steps(sampled) if batch is None else batch  # ``steps``, when known
        nxt = batch[keys.NEXT]
        next_obs = self.inputs(sampled, after=True)
        params = self.policy_params(next_obs)
        sampled: list[torch.Tensor] = []
        if self.continuous:
            next_action, next_log_prob = self._sample(params[0], params[1])
            sampled = [next_action]
        next_q = self.q_values(self.q_target, next_obs, sampled)  # [2, B, streams, outputs]
        if not self.branches:
            entropy = alpha[0] * next_log_prob.unsqueeze(-1)
            next_value = (next_q.squeeze(-1) - entropy).min(0).values  # [B, streams]
        else:
            mask, a = nxt[keys.ACTION_MASK], alpha[int(self.continuous) :]
            next_value = expected_value(params[-1], mask, next_q.min(0).values, a, self.branches)
            if self.continuous:
                next_value = next_value - alpha[0] * next_log_prob.unsqueeze(-1)
        gamma = torch.full((1,), self.settings.gamma, device=next_value.device)
        ends = torch.zeros(1, dtype=torch.bool, device=next_value.device)  # extrinsic: stops
        reward = nxt[keys.REWARD]  # [B, 1]
        if self.signals:
            gamma = torch.cat([gamma, self.signals.gammas])
            ends = torch.cat([ends, self.signals.ignore_done])
            reward = torch.cat([reward, self.signals.rewards(batch)], dim=-1)
        going = ~nxt[keys.TERMINATED] | ends  # [B, streams]: the stream goes on after it
        return reward + gamma * going.to(next_value.dtype) * next_value

    def _sample(self, loc: torch.Tensor, scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterized tanh-squashed action in [-1, 1] and its log-probability."""
        dist = TanhNormal(loc, scale, low=-1.0, high=1.0)
        action = dist.rsample()
        return action, dist.log_prob(action)

    # --- checkpoints --------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Optimizers, Q and target-Q weights, the entropy coefficient, the signals; not
        the buffer. The policy's weights travel with the network, so they are left out."""
        return {
            "signals": self.signals.state_dict(),
            "q": self.q.state_dict(),
            "q_target": self.q_target.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "alpha_optimizer": self.alpha_optimizer.state_dict(),
            "gradient_steps": self.gradient_steps,
            "dropped_gradient_steps": self.dropped_gradient_steps,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.q.load_state_dict(state["q"])
        self.q_target.load_state_dict(state["q_target"])
        with torch.no_grad():  # (a checkpoint of one part may hold a scalar)
            self.log_alpha.copy_(state["log_alpha"].reshape(self.log_alpha.shape))
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.alpha_optimizer.load_state_dict(state["alpha_optimizer"])
        self.gradient_steps = int(state["gradient_steps"])
        self.dropped_gradient_steps = int(state["dropped_gradient_steps"])
        if self.signals:
            self.signals.load_state_dict(state["signals"])
