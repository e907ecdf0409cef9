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

from learners.modules import FLAT_ACTION, probabilistic_actor, value_operator
from learners.onpolicy import (
    TRAIN,
    SegmentBuffer,
    actor_critic_report,
    gradient_step,
    means,
    set_learning_rate,
)
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
        self.buffer = SegmentBuffer(h.buffer_size)
        self.stale_steps = 0

    # --- data in ------------------------------------------------------------------------

    def add(self, segment: TensorDict, lag: torch.Tensor) -> int:
        """Buffer a ``[B, T]`` segment (``lag``: per step, updates of this behavior since
        the weights that acted); returns the steps that will count in the loss."""
        fresh = lag <= self.settings.hyperparameters.max_policy_lag
        self.stale_steps += int((~fresh).sum())
        return self.buffer.add(segment, keep=fresh)

    def ready(self) -> bool:
        return self.buffer.ready()

    def wanted(self) -> int | None:
        return self.buffer.wanted()

    # --- the update ---------------------------------------------------------------------

    def update(self, progress: float) -> dict[str, float]:
        """One PPO iteration on everything buffered; ``progress`` in [0, 1] drives schedules."""
        h = self.settings.hyperparameters
        batch = self.buffer.take(self.network, self.settings.reward_strength)
        with torch.no_grad():
            self.advantage(batch)
        steps = batch[batch[TRAIN]]  # the steps that train, each with advantage and target

        lr = linear_decay(h.learning_rate, progress, h.learning_rate_schedule)
        set_learning_rate(self.optimizer, lr)
        totals: dict[str, float] = {}
        for _ in range(h.num_epoch):
            for index in torch.randperm(len(steps)).split(h.batch_size):
                if len(index) > 1:
                    gradient_step(self.loss, steps[index], self.optimizer, self.network, totals)
        mean = means(totals)
        return {
            **actor_critic_report(mean, lr, h.beta),
            "Policy/Epsilon": h.epsilon,
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
