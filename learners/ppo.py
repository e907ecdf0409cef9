"""PPO for one behavior, on torchrl pieces: ``ClipPPOLoss`` and ``GAE``.

Reads top to bottom like one iteration of the algorithm: segments arrive (``add``) and
wait in a buffer until ``buffer_size`` valid steps are there; ``update`` folds their
observations into the running normalization, computes GAE advantages on the ``[B, T]``
rows (torchrl's estimator, which stops at ``done`` and bootstraps from the next
observation unless ``terminated``), flattens the valid steps, and runs ``num_epoch``
passes of shuffled minibatches through the clipped surrogate.

Policy lag: workers act with slightly old weights. The surrogate's ratio is taken
against the log-probability stored with each step (the policy that really acted), which
corrects moderate lag; steps acted by weights more than ``max_policy_lag`` versions old
are dropped from the loss (they still serve as GAE context) and counted.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from learners.modules import FLAT_ACTION, add_flat_action, probabilistic_actor, value_operator
from learners.policies import ActorCritic
from learners.schedules import linear_decay
from rollout import keys

if TYPE_CHECKING:
    from learners.config import TrainerSettings


class PPO:
    def __init__(self, network: ActorCritic, settings: TrainerSettings) -> None:
        self.network, self.settings = network, settings
        h = settings.hyperparameters
        actor, critic = probabilistic_actor(network), value_operator(network)
        self.loss = ClipPPOLoss(
            actor,
            critic,
            clip_epsilon=h.epsilon,
            entropy_coeff=h.beta,
            critic_coeff=0.5,
            loss_critic_type="l2",
            normalize_advantage=True,
            functional=False,  # actor and critic share encoders: use the modules as they are
        )
        self.loss.set_keys(action=FLAT_ACTION, sample_log_prob=keys.LOG_PROB)
        self.advantage = GAE(
            gamma=settings.gamma, lmbda=h.lambd, value_network=critic, average_gae=False
        )
        self.optimizer = torch.optim.Adam(network.parameters(), lr=h.learning_rate)
        self.pending: list[TensorDict] = []
        self.pending_steps = 0
        self.stale_steps = 0

    # --- data in ------------------------------------------------------------------------

    def add(self, segment: TensorDict, version: int) -> int:
        """Buffer a ``[B, T]`` segment; returns the steps that will count in the loss."""
        segment = segment.exclude(*keys.METADATA)
        fresh = (
            version - segment[keys.POLICY_VERSION] <= self.settings.hyperparameters.max_policy_lag
        )
        valid = segment[keys.VALID]
        self.stale_steps += int((valid & ~fresh).sum())
        segment[keys.VALID] = valid & fresh
        steps = int(segment[keys.VALID].sum())
        if steps:
            self.pending.append(segment)
            self.pending_steps += steps
        return steps

    def ready(self) -> bool:
        return self.pending_steps >= self.settings.hyperparameters.buffer_size

    # --- the update ---------------------------------------------------------------------

    def update(self, progress: float) -> dict[str, float]:
        """One PPO iteration on everything buffered; ``progress`` in [0, 1] drives schedules."""
        h = self.settings.hyperparameters
        batch = torch.cat(self.pending, dim=0)
        self.pending, self.pending_steps = [], 0
        valid = batch[keys.VALID]

        obs = batch[keys.OBS]
        self.network.update_normalization({n: obs[n][valid] for n in obs.keys()})  # noqa: SIM118
        batch[keys.NEXT, keys.REWARD] = (
            batch[keys.NEXT, keys.REWARD] * self.settings.reward_strength
        )
        add_flat_action(batch)
        with torch.no_grad():
            self.advantage(batch)
        steps = batch[valid]  # [N]: the valid steps, each with its advantage and target

        lr = linear_decay(h.learning_rate, progress, h.learning_rate_schedule)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        totals: dict[str, float] = {}
        updates = 0
        for _ in range(h.num_epoch):
            for index in torch.randperm(len(steps)).split(h.batch_size):
                if len(index) < 2:
                    continue
                losses = self.loss(steps[index])
                loss = sum(v for k, v in losses.items() if k.startswith("loss_"))
                self.optimizer.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.network.parameters(), 0.5)
                self.optimizer.step()
                for key, value in losses.items():
                    totals[key] = totals.get(key, 0.0) + float(value.detach().mean())
                updates += 1
        mean = {key: value / max(updates, 1) for key, value in totals.items()}
        return {
            "Losses/Policy Loss": mean.get("loss_objective", 0.0),
            "Losses/Value Loss": mean.get("loss_critic", 0.0) * 2,  # undo critic_coeff 0.5
            "Policy/Entropy": mean.get("entropy", 0.0),
            "Policy/Learning Rate": lr,
            "Policy/Epsilon": h.epsilon,
            "Policy/Beta": h.beta,
            "Policy/Clip Fraction": mean.get("clip_fraction", 0.0),
            "Policy/Approx KL": mean.get("kl_approx", 0.0),
            "Policy/Extrinsic Value Estimate": float(steps["state_value"].mean()),
            "Policy/Stale Steps Dropped": float(self.stale_steps),
            "Policy/Samples": float(len(steps)),
        }

    # --- checkpoints --------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {"optimizer": self.optimizer.state_dict(), "stale_steps": self.stale_steps}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
        self.stale_steps = int(state.get("stale_steps", 0))
