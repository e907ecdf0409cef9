"""SAC for one behavior: continuous actions or a single masked discrete branch, with
torchrl's ``TensorDictReplayBuffer`` and ``TanhNormal``; the losses written out in torch.

``add`` turns every step of a packed segment into a transition (obs, action,
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

The math is torchrl's ``SACLoss`` / ``DiscreteSACLoss`` (v2, two Q networks, l2), which
this file used until 2026-11-25; written out, a gradient step on 3DBall's network takes
a third of the time: the functional-parameter bookkeeping of those losses cost more than
the tiny networks (docs/benchmarks.md).

Off-policy by design: the policy lag ``add`` gets is ignored. The replay buffer is not in
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
from learners.devices import Compute
from learners.modules import PolicyParams
from learners.policies import ActorCritic, SensorEncoder
from learners.schedules import decay

if TYPE_CHECKING:
    from learners.settings import TrainerSettings

ACTION = "action"  # replay buffer: continuous float [c], or the discrete index (int64 [])
MAX_GRADIENT_STEPS = 200  # per update() call, so one call stays short; the rest is dropped
MASKED_LOGIT = -1e8  # finite, so p * log p is 0 (not nan) for masked actions
DISCRETE_TARGET_ENTROPY_SCALE = 0.2  # ML-Agents' discrete_target_entropy_scale
TINY_PROBABILITY = 1e-8  # log p of a masked action in the target (its weight p is 0)


class QNetwork(nn.Module):
    """Q(obs, action) -> [1] (continuous) or Q(obs) -> [actions] (discrete).

    Own encoders (the policy's ``vis_encode_type`` per image sensor, as ML-Agents gives
    each Q network its own body) over observations normalized with the policy's running
    statistics, read but never trained here; then a SiLU MLP of the behavior's hidden
    units and layers.
    """

    def __init__(self, network: ActorCritic, outputs: int, action_size: int = 0) -> None:
        super().__init__()
        self.norms = [e.norm for e in network.encoders]  # a list: not submodules/params
        self.encoders = nn.ModuleList(
            SensorEncoder(o.shape, network.settings, sensor=o.name)
            for o in network.spec.observation_specs
        )
        width = sum(e.size for e in self.encoders) + action_size
        layers: list[nn.Module] = []
        for _ in range(network.settings.num_layers):
            layers += [nn.Linear(width, network.settings.hidden_units), nn.SiLU()]
            width = network.settings.hidden_units
        self.body = nn.Sequential(*layers, nn.Linear(width, outputs))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        parts = []
        for encoder, norm, x in zip(self.encoders, self.norms, inputs, strict=False):
            x = encoder(x)
            parts.append(norm(x) if norm is not None else x)
        parts += inputs[len(self.encoders) :]  # the action, for continuous Q
        return self.body(torch.cat(parts, dim=-1))


def masked_logits(logits: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Masked actions (mask False) get a finite logit of probability exactly 0."""
    return logits if mask is None else logits.masked_fill(~mask, MASKED_LOGIT)


class SAC:
    def __init__(
        self, network: ActorCritic, settings: TrainerSettings, compute: Compute | None = None
    ) -> None:
        self.compute = compute or Compute()
        branches = network.branches
        if (
            (network.continuous and branches)
            or len(branches) > 1
            or not (network.continuous or branches)
        ):
            raise ValueError(
                "SAC supports continuous actions or a single discrete branch; use ppo for "
                f"hybrid or multi-branch actions (got continuous={network.continuous}, "
                f"branches={branches})"
            )
        self.network, self.settings = network, settings
        self.continuous = bool(network.continuous)
        h = settings.hyperparameters
        device = self.compute.torch_device
        self.policy = PolicyParams(network)  # (loc, scale) or (logits,)
        outputs, action_size = (1, network.continuous) if self.continuous else (branches[0], 0)
        self.q = nn.ModuleList(QNetwork(network, outputs, action_size) for _ in range(2))
        self.q.to(device)
        self.q_target = copy.deepcopy(self.q).requires_grad_(False)
        for target, q in zip(self.q_target, self.q, strict=True):
            target.norms = q.norms  # the policy's running statistics, not frozen copies
        self.log_alpha = torch.tensor(math.log(h.init_entcoef), device=device, requires_grad=True)
        self.target_entropy = (
            -float(network.continuous)
            if self.continuous
            else DISCRETE_TARGET_ENTROPY_SCALE * math.log(branches[0])
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
            storage=LazyTensorStorage(h.buffer_size, device=device, compilable=True),
            batch_size=h.batch_size,
            compilable=True,
        )
        self.tau = h.tau
        self.threshold = max(h.buffer_init_steps, h.batch_size)
        self.received = 0  # valid steps added, ever
        self.new_steps = 0.0  # steps past the threshold not yet paid in gradient steps
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
        action = (
            segment[keys.ACTION, keys.CONTINUOUS]
            if self.continuous
            else segment[keys.ACTION, keys.DISCRETE][..., 0]
        )
        transitions = TensorDict(
            {
                keys.OBS: segment[keys.OBS],
                ACTION: action,
                keys.NEXT: {
                    keys.OBS: nxt[keys.OBS],
                    keys.REWARD: nxt[keys.REWARD] * self.settings.reward_strength,
                    keys.DONE: nxt[keys.DONE],
                    keys.TERMINATED: nxt[keys.TERMINATED],
                },
            },
            batch_size=segment.batch_size,
        )
        if not self.continuous:
            mask = segment[keys.ACTION_MASK]
            transitions[keys.ACTION_MASK] = mask
            transitions[keys.NEXT, keys.ACTION_MASK] = next_mask(mask, nxt[keys.DONE])
        self.network.update_normalization(transitions[keys.OBS].to_dict())
        self.buffer.extend(transitions)
        before = self.received
        self.received += steps
        self.new_steps += max(0, self.received - max(before, self.threshold))
        return steps

    def ready(self) -> bool:
        h = self.settings.hyperparameters
        return len(self.buffer) >= self.threshold and self.new_steps >= h.steps_per_update

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
        mean = {key: float(value) / max(count, 1) for key, value in totals.items()}
        # each Q's loss and estimate: of the last step only (one sync, not one per step)
        mean.update({key: float(last[key]) for key in ("q1", "q2", "estimate") if key in last})
        return {
            "Losses/Policy Loss": mean.get("policy", 0.0),
            "Losses/Q1 Loss": mean.get("q1", 0.0),
            "Losses/Q2 Loss": mean.get("q2", 0.0),
            "Losses/Entropy Coeff Loss": mean.get("alpha_loss", 0.0),
            "Policy/Entropy Coeff": float(self.log_alpha.detach().exp()),
            "Policy/Entropy": mean.get("entropy", 0.0),
            "Policy/Learning Rate": lr,
            "Policy/Extrinsic Value Estimate": mean.get("estimate", 0.0),
            "Policy/Gradient Steps": float(count),
            "Policy/Dropped Gradient Steps": float(self.dropped_gradient_steps),
            "Policy/Samples": float(count * h.batch_size),
        }

    def gradient_step(self, batch: TensorDict) -> dict[str, torch.Tensor]:
        """One step of all three losses on a sampled batch (each computed with the
        weights before the step, summed, one backward), then the Polyak target update.
        Returns detached scalars: the losses, the entropy, each Q's squared TD error and
        the mean Q of the stored actions."""
        obs = [batch[keys.OBS, name] for name in self.network.sensor_names]
        alpha = self.log_alpha.detach().exp()
        target = self.target(batch, alpha)  # its draw of a' comes first, as in torchrl's
        if self.continuous:
            taken = torch.stack([q(*obs, batch[ACTION]) for q in self.q]).squeeze(-1)
            action, log_prob = self._sample(obs)
            for param in self._q_params:  # the actor's gradient reaches the action only
                param.requires_grad_(False)
            policy_q = torch.stack([q(*obs, action) for q in self.q]).min(0).values.squeeze(-1)
            for param in self._q_params:
                param.requires_grad_(True)
            policy_loss = (alpha * log_prob - policy_q).mean()
            neg_entropy = log_prob.detach()
        else:
            values = torch.stack([q(*obs) for q in self.q])  # [2, B, actions]
            index = batch[ACTION].view(1, -1, 1).expand(2, -1, 1)
            taken = values.gather(-1, index).squeeze(-1)
            logits = masked_logits(self.policy(*obs)[0], batch.get(keys.ACTION_MASK))
            log_prob = torch.log_softmax(logits, dim=-1)
            prob = log_prob.exp()
            policy_q = values.detach().min(0).values
            policy_loss = (prob * (alpha * log_prob - policy_q)).sum(-1).mean()
            neg_entropy = (prob * log_prob).sum(-1).detach()
        errors = (taken - target).square().mean(-1)  # [2]: each Q's mean squared TD error
        alpha_loss = -(self.log_alpha * (neg_entropy + self.target_entropy)).mean()
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
            "entropy": -neg_entropy.mean(),
            "q1": errors[0],
            "q2": errors[1],
            "estimate": taken.detach().mean(),
        }

    @torch.no_grad()
    def target(self, batch: TensorDict, alpha: torch.Tensor) -> torch.Tensor:
        """``r + gamma (1 - terminated) V(s')`` with the target Qs: ``V`` of a fresh
        ``a' ~ pi(s')`` (continuous) or the expectation over the masked softmax."""
        nxt = batch[keys.NEXT]
        next_obs = [nxt[keys.OBS, name] for name in self.network.sensor_names]
        if self.continuous:
            next_action, next_log_prob = self._sample(next_obs)
            next_q = torch.stack([q(*next_obs, next_action) for q in self.q_target])
            next_value = (next_q.squeeze(-1) - alpha * next_log_prob).min(0).values
        else:
            logits = masked_logits(self.policy(*next_obs)[0], nxt.get(keys.ACTION_MASK))
            next_prob = torch.softmax(logits, dim=-1)
            next_log_prob = torch.where(next_prob == 0, TINY_PROBABILITY, next_prob).log()
            next_q = torch.stack([q(*next_obs) for q in self.q_target]).min(0).values
            next_value = (next_prob * (next_q - alpha * next_log_prob)).sum(-1)
        not_terminated = (~nxt[keys.TERMINATED]).squeeze(-1).to(next_value.dtype)
        reward = nxt[keys.REWARD].squeeze(-1)
        return reward + self.settings.gamma * not_terminated * next_value

    def _sample(self, obs: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterized tanh-squashed action in [-1, 1] and its log-probability."""
        loc, scale = self.policy(*obs)
        dist = TanhNormal(loc, scale, low=-1.0, high=1.0)
        action = dist.rsample()
        return action, dist.log_prob(action)

    # --- checkpoints --------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Optimizers, Q and target-Q weights, the entropy coefficient; not the buffer.
        The policy's weights travel with the network, so they are left out here."""
        return {
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
        if "q" not in state:
            raise ValueError(
                "this checkpoint's SAC state predates 2026-11-25 (torchrl's SACLoss layout); "
                "start a new run (another --run-id) instead of resuming it"
            )
        self.q.load_state_dict(state["q"])
        self.q_target.load_state_dict(state["q_target"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.alpha_optimizer.load_state_dict(state["alpha_optimizer"])
        self.gradient_steps = int(state.get("gradient_steps", 0))
        self.dropped_gradient_steps = int(state.get("dropped_gradient_steps", 0))


def next_mask(mask: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
    """The allowed-mask of each step's next state: the next step's own mask when it is in
    the same trajectory (packed trajectories end with ``done``); otherwise (episode end,
    horizon cut) all allowed, as no mask was observed for that state."""
    result = torch.ones_like(mask)
    follows = ~done[:-1, 0]
    result[:-1] = torch.where(follows.unsqueeze(-1), mask[1:], True)
    return result
