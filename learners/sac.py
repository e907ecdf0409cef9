"""SAC for one behavior, on torchrl pieces: ``SACLoss`` / ``DiscreteSACLoss``, ``SoftUpdate``
and a ``TensorDictReplayBuffer``; continuous actions or a single masked discrete branch.

``add`` turns every step of a packed segment into a transition (obs, action,
reward * strength, next obs, terminated, done; discrete: the masks of both states) in a
replay buffer of ``buffer_size`` steps. ``ready`` once it holds ``max(buffer_init_steps,
batch_size)`` steps and ``steps_per_update`` new ones came. ``update`` takes one gradient
step per ``steps_per_update`` new steps (at most ``MAX_GRADIENT_STEPS``), each on
``batch_size`` sampled transitions: twin Q regress to ``r + gamma (1 - terminated)
(min Q_target(s', a') - alpha log pi(a'|s'))``, the tanh-squashed policy minimizes
``alpha log pi - min Q`` (discrete: the exact expectation over the masked softmax), alpha
tracks the "auto" target entropy; then the target Qs move by ``tau`` (Polyak).

Off-policy by design: the policy lag ``add`` gets is ignored. The replay buffer is not in
``state_dict`` (a resumed run refills it before updating again).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict
from tensordict.nn import ProbabilisticTensorDictModule, ProbabilisticTensorDictSequential
from torch import nn
from torchrl.data import Bounded, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.modules import TanhNormal
from torchrl.objectives import DiscreteSACLoss, SACLoss, SoftUpdate

from learners.devices import Compute
from learners.modules import PolicyParams, TensorModule, obs_keys
from learners.policies import ActorCritic, SensorEncoder
from learners.schedules import decay
from rollout import keys

if TYPE_CHECKING:
    from learners.config import TrainerSettings

ACTION = "action"  # replay buffer: continuous float [c], or the discrete index (int64 [])
MAX_GRADIENT_STEPS = 200  # per update() call, so one call stays short; the rest is dropped
MASKED_LOGIT = -1e8  # finite, so p * log p is 0 (not nan) for masked actions
DISCRETE_TARGET_ENTROPY_SCALE = 0.2  # ML-Agents' discrete_target_entropy_scale


class MaskedSoftmax(torch.distributions.Categorical):
    """One branch's categorical: masked actions (mask False) get probability exactly 0 and
    a finite log-probability, as ``DiscreteSACLoss`` sums ``p * (alpha log p - Q)``."""

    def __init__(self, logits: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        if mask is not None:
            logits = logits.masked_fill(~mask, MASKED_LOGIT)
        super().__init__(logits=logits, validate_args=False)


class QNetwork(nn.Module):
    """Q(obs, action) -> [1] (continuous) or Q(obs) -> [actions] (discrete).

    Own encoders (the policy's ``vis_encode_type`` per image sensor, as ML-Agents gives
    each Q network its own body) over observations normalized with the policy's running
    statistics, read but never trained here; then a SiLU MLP of the behavior's hidden
    units and layers.
    """

    def __init__(self, network: ActorCritic, outputs: int, action_size: int = 0) -> None:
        super().__init__()
        self._norms = [e.norm for e in network.encoders]  # a list: not submodules/params
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
        for encoder, norm, x in zip(self.encoders, self._norms, inputs, strict=False):
            x = encoder(x)
            parts.append(norm(x) if norm is not None else x)
        parts += inputs[len(self.encoders) :]  # the action, for continuous Q
        return self.body(torch.cat(parts, dim=-1))


class _TargetKeepingSACLoss(SACLoss):
    """torchrl's SACLoss; keeps the last TD target so each Q loss can be reported."""

    def _compute_target_v2(self, tensordict: TensorDict) -> torch.Tensor:
        self.last_target = super()._compute_target_v2(tensordict)
        return self.last_target


class _TargetKeepingDiscreteSACLoss(DiscreteSACLoss):
    def _compute_target(self, tensordict: TensorDict) -> torch.Tensor:
        self.last_target = super()._compute_target(tensordict)
        return self.last_target


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
        h = settings.hyperparameters
        obs = obs_keys(network)
        params = TensorModule(
            PolicyParams(network),
            in_keys=obs,
            out_keys=["loc", "scale"] if network.continuous else ["logits"],
        )
        if network.continuous:
            self.actor = ProbabilisticTensorDictSequential(
                params,
                ProbabilisticTensorDictModule(
                    in_keys=["loc", "scale"],
                    out_keys=[ACTION],
                    distribution_class=TanhNormal,
                    distribution_kwargs={"low": -1.0, "high": 1.0},
                ),
            )
            qs = [
                TensorModule(
                    QNetwork(network, 1, network.continuous),
                    in_keys=[*obs, ACTION],
                    out_keys=["state_action_value"],
                )
                for _ in range(2)
            ]
            self.loss: SACLoss | DiscreteSACLoss = _TargetKeepingSACLoss(
                self.actor,
                qs,
                loss_function="l2",
                alpha_init=h.init_entcoef,
                action_spec=Bounded(-1.0, 1.0, shape=(network.continuous,)),
                target_entropy="auto",  # -(action dims)
            )
            self.q_out = "state_action_value"
        else:
            self.actor = ProbabilisticTensorDictSequential(
                params,
                ProbabilisticTensorDictModule(
                    in_keys={"logits": "logits", "mask": keys.ACTION_MASK},
                    out_keys=[ACTION],
                    distribution_class=MaskedSoftmax,
                ),
            )
            qs = [
                TensorModule(QNetwork(network, branches[0]), in_keys=obs, out_keys=["action_value"])
                for _ in range(2)
            ]
            self.loss = _TargetKeepingDiscreteSACLoss(
                self.actor,
                qs,
                action_space="categorical",
                num_actions=branches[0],
                loss_function="l2",
                alpha_init=h.init_entcoef,
                target_entropy="auto",  # scale * log(actions)
                target_entropy_weight=DISCRETE_TARGET_ENTROPY_SCALE,
            )
            self.q_out = "action_value"
        self.loss.to(self.compute.torch_device)  # the Q networks, their targets, alpha
        self.loss.make_value_estimator(gamma=settings.gamma)  # TD(0): r + gamma V(s')
        self.target_update = SoftUpdate(self.loss, tau=h.tau)
        self.actor_optimizer = torch.optim.Adam(
            network.parameters(), lr=h.learning_rate, fused=True
        )
        self.critic_optimizer = torch.optim.Adam(
            list(self.loss.qvalue_network_params.values(True, True)),
            lr=h.learning_rate,
            fused=True,
        )
        self.alpha_optimizer = torch.optim.Adam(
            [self.loss.log_alpha], lr=h.learning_rate, fused=True
        )
        self.optimizers = (self.actor_optimizer, self.critic_optimizer, self.alpha_optimizer)
        # compilable: plain counters, not multiprocessing.Value (this buffer never leaves
        # the learner process, and mp.Value would start a resource-tracker process)
        self.buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(
                h.buffer_size, device=self.compute.torch_device, compilable=True
            ),
            batch_size=h.batch_size,
            compilable=True,
        )
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
            if self.network.continuous
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
        if self.network.branches:
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
        totals: dict[str, float] = {}
        for index in range(count):
            batch = self.buffer.sample()
            for key, value in self.gradient_step(batch).items():
                totals[key] = totals.get(key, 0.0) + value
            if index == count - 1:  # each Q's own loss costs two more passes: one batch
                totals.update(self.q_losses(batch))
        self.gradient_steps += count
        mean = {key: value / max(count, 1) for key, value in totals.items()}
        mean.update({key: totals[key] for key in ("q1", "q2", "estimate") if key in totals})
        return {
            "Losses/Policy Loss": mean.get("policy", 0.0),
            "Losses/Q1 Loss": mean.get("q1", 0.0),
            "Losses/Q2 Loss": mean.get("q2", 0.0),
            "Losses/Entropy Coeff Loss": mean.get("alpha_loss", 0.0),
            "Policy/Entropy Coeff": float(self.loss.log_alpha.detach().exp()),
            "Policy/Entropy": mean.get("entropy", 0.0),
            "Policy/Learning Rate": lr,
            "Policy/Extrinsic Value Estimate": mean.get("estimate", 0.0),
            "Policy/Gradient Steps": float(count),
            "Policy/Dropped Gradient Steps": float(self.dropped_gradient_steps),
            "Policy/Samples": float(count * h.batch_size),
        }

    def gradient_step(self, batch: TensorDict) -> dict[str, float]:
        """One step of all three losses on a sampled batch, then the Polyak target update."""
        losses = self.loss(batch)
        loss = losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_alpha"]
        for optimizer in self.optimizers:
            optimizer.zero_grad()
        loss.backward()  # the actor loss sees detached Qs; Q targets carry no gradient
        for optimizer in self.optimizers:
            optimizer.step()
        self.target_update.step()
        return {
            "policy": float(losses["loss_actor"].detach()),
            "alpha_loss": float(losses["loss_alpha"].detach()),
            "entropy": float(losses["entropy"]),
        }

    @torch.no_grad()
    def q_losses(self, batch: TensorDict) -> dict[str, float]:
        """Each Q network's squared TD error on the batch just trained on (torchrl reports
        their sum), and the mean Q of the stored actions."""
        target = self.loss.last_target
        module = self.loss.qvalue_network
        predictions = []
        for index in range(2):
            with self.loss.qvalue_network_params[index].to_module(module):
                q = module(batch.select(*module.in_keys).clone(False))[self.q_out]
            if self.q_out == "action_value":
                q = q.gather(-1, batch[ACTION].unsqueeze(-1))
            predictions.append(q.squeeze(-1))
        q1, q2 = ((q - target).square().mean() for q in predictions)
        return {
            "q1": float(q1),
            "q2": float(q2),
            "estimate": float((predictions[0] + predictions[1]).mean() / 2),
        }

    # --- checkpoints --------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Optimizers, Q and target-Q weights, the entropy coefficient; not the buffer.
        The policy's weights travel with the network, so they are left out here."""
        loss = {
            k: v
            for k, v in self.loss.state_dict().items()
            if not k.startswith("actor_network_params")
        }
        return {
            "loss": loss,
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "alpha_optimizer": self.alpha_optimizer.state_dict(),
            "gradient_steps": self.gradient_steps,
            "dropped_gradient_steps": self.dropped_gradient_steps,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        missing, unexpected = self.loss.load_state_dict(state["loss"], strict=False)
        assert not unexpected, unexpected
        assert all(k.startswith("actor_network_params") for k in missing), missing
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
