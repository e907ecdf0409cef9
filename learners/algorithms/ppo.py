"""PPO for one behavior, as mlagents-learn runs it, on torchrl's vectorized GAE.

Reads top to bottom like one iteration of the algorithm, as mlagents-learn runs it:
segments arrive (``add``) and are written into the trajectory store
(``learners/algorithms/trajectory_store.py``: preallocated on the learner's device, each observation
once) until more than ``buffer_size`` steps are there; ``update`` folds their observations
into the running normalization, computes GAE advantages along each packed trajectory
(torchrl's ``vec_generalized_advantage_estimate``: ``done`` stops the trace, the
bootstrap is the next row's value, or at a truncated end its kept next observation's, and
0 where ``terminated``), normalizes the advantages over the whole buffer, and runs
``num_epoch`` passes of shuffled minibatches of ``batch_size`` (the remainder left out)
through ``loss``, each minibatch one gather per field from the store. Learning rate,
epsilon and beta decay linearly over ``max_steps`` to 1e-10, 0.1 and 1e-5, as ML-Agents'
do (``*_schedule: constant`` keeps them). No gradient clipping, as in ML-Agents.

The loss is ML-Agents', written out rather than torchrl's ``ClipPPOLoss``, because
``epsilon`` means something else there: ML-Agents clips the probability ratio of each
action component (each continuous dimension, each discrete branch) on its own and
averages the clipped surrogates; ``ClipPPOLoss`` clips the ratio of the joint action.
The value loss is the plain squared error, which is what mlagents-learn 1.1.0 computes
in effect: its code clips the value around the old estimate, but the old estimate it
reads is the return (``RewardSignalUtil.value_estimates_key`` names the returns' buffer
field), so the clip never binds. Clipping for real cost samples: 3DBall reached 90 at
a median 138k steps against 114k without (docs/benchmarks-log.md, "every difference
we found").

Policy lag: workers act with slightly old weights. The surrogate's ratio is taken
against the log-probability stored with each step (the policy that really acted), which
corrects moderate lag. Every step trains, as in mlagents-learn; with ``max_policy_lag``
set, steps acted by weights more than that many versions old are dropped from the loss
(they still serve as GAE context) and counted. Dropping them lost learning with 16 workers
(docs/benchmarks-log.md, "policy lag").
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict
from torchrl.objectives.value.functional import vec_generalized_advantage_estimate

from learners.algorithms.minibatch import (
    REPORTED,
    MinibatchStep,
    adam,
    load_optimizer,
    plain_learning_rates,
    set_learning_rate,
)
from learners.algorithms.schedules import BETA_END, EPSILON_END, decay
from learners.algorithms.trajectory_store import Rows, TrajectoryStore
from learners.host.counters import on_policy_wanted
from learners.host.devices import Compute
from learners.networks.policies import ActorCritic
from learners.reward_signals.ppo_streams import Signals

if TYPE_CHECKING:
    from collections.abc import Mapping

    from batches.expert_steps import ExpertSteps
    from learners.trainer_config.settings import TrainerSettings

VALUE_CHUNK_BYTES = 256 * 2**20


# ---- pieces IMPALA shares -------------------------------------------------------------------


def value_chunk(obs: dict[str, torch.Tensor], entities: int = 1) -> int:
    """How many rows (of ``entities`` observations each) hold about ``VALUE_CHUNK_BYTES``
    of float input: values are computed in chunks of it, so a large observation is never
    converted whole."""
    width = sum(math.prod(o.shape[1:]) for o in obs.values()) * 4 * entities  # float32
    return max(1, VALUE_CHUNK_BYTES // max(width, 1))


def policy_terms(
    log_prob: torch.Tensor,
    entropy: torch.Tensor,
    steps: Steps,
    epsilon: float | torch.Tensor,
    beta: float | torch.Tensor,
) -> dict[str, torch.Tensor]:
    """ML-Agents' clipped surrogate (each action component's ratio clipped on its own,
    the clipped surrogates averaged) and entropy bonus, with their diagnostics."""
    log_ratio = log_prob - steps.log_prob
    ratio = log_ratio.exp()  # [B, components]
    advantage = steps.advantage.unsqueeze(-1)
    surrogate = torch.min(ratio * advantage, ratio.clamp(1 - epsilon, 1 + epsilon) * advantage)
    entropy, objective = entropy.mean(), -surrogate.mean()
    return {
        "loss_objective": objective,
        "objective_size": objective.detach().abs(),
        "loss_entropy": -beta * entropy,
        "entropy": entropy.detach(),
        "clip_fraction": ((ratio.detach() - 1.0).abs() > epsilon).float().mean(),
        "kl_approx": -log_ratio.detach().mean(),
    }


def actor_critic_report(mean: dict[str, float], lr: float, beta: float) -> dict[str, float]:
    """ML-Agents' names for an actor-critic loss's means over one update."""
    return {
        # ML-Agents reports each minibatch's |policy loss|, averaged over the update
        "Losses/Policy Loss": mean.get("objective_size", 0.0),
        "Losses/Value Loss": mean.get("loss_critic", 0.0) * 2,  # undo critic_coeff 0.5
        "Policy/Entropy": mean.get("entropy", 0.0),
        "Policy/Learning Rate": lr,
        "Policy/Beta": beta,
    }


# ---- PPO ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Steps:
    """The steps of one update as plain tensors, ``[N, ...]`` each: a minibatch is then
    one gather per field (a TensorDict's per-key bookkeeping cost as much as the network)."""

    obs: dict[str, torch.Tensor]
    continuous: torch.Tensor | None
    discrete: torch.Tensor | None
    mask: torch.Tensor | None  # True = allowed
    log_prob: torch.Tensor  # [N, components], the acting policy's
    advantage: torch.Tensor  # [N]
    value_target: torch.Tensor  # [N]

    @classmethod
    def of(cls, rows: Rows, advantage: torch.Tensor, value_target: torch.Tensor) -> Steps:
        fields = (rows.obs, rows.continuous, rows.discrete, rows.mask, rows.log_prob)
        return cls(*fields, advantage, value_target)

    def __getitem__(self, index: torch.Tensor) -> Steps:
        def pick(tensor: torch.Tensor | None) -> torch.Tensor | None:
            return None if tensor is None else tensor[index]

        return Steps(
            {name: obs[index] for name, obs in self.obs.items()},
            pick(self.continuous),
            pick(self.discrete),
            pick(self.mask),
            self.log_prob[index],
            self.advantage[index],
            self.value_target[index],
        )


class PPO:
    groupmates = False  # the store keeps each step's groupmates (POCA)
    reported = REPORTED  # the loss entries an update reports

    def __init__(
        self,
        network: ActorCritic,
        settings: TrainerSettings,
        compute: Compute | None = None,
        experts: Mapping[str, ExpertSteps] | None = None,
    ) -> None:
        """``experts``: the demonstrations of a ``gail`` signal, by ``demo_path``."""
        self.network, self.settings = network, settings
        self.compute = compute or Compute()
        h = settings.hyperparameters
        device = self.compute.torch_device
        self.signals = Signals(network, settings.reward_signals, device, experts)
        self.optimizer = adam(self.trained_parameters(), h.learning_rate, self.compute)
        self.store = TrajectoryStore(
            h.buffer_size,
            device,
            self.groupmates,
            terminal_obs=self.signals.terminal_obs,
            episodes=bool(self.signals),
        )
        self.step = MinibatchStep(
            self._minibatch_loss, self.optimizer, h.batch_size, self.compute, self.reported
        )
        self._bound: Steps | None = None  # the store's columns whole: what ``step`` reads
        self._targets: torch.Tensor | None = None  # [2, capacity]: advantage, value target
        self.stale_steps = 0

    def trained_parameters(self) -> list[torch.nn.Parameter]:
        """The network's, and the intrinsic signals' value heads (their own networks have
        optimizers of their own)."""
        return [*self.network.parameters(), *self.signals.heads.parameters()]

    # --- data in ------------------------------------------------------------------------

    def add(self, segment: TensorDict, lag: torch.Tensor) -> int:
        """Store a packed segment (``lag``: per step, updates of this behavior since the
        weights that acted); returns the steps that will count in the loss."""
        limit = self.settings.hyperparameters.max_policy_lag
        if limit is None:  # every step trains
            return self.store.add(segment)
        fresh = lag <= limit
        self.stale_steps += int((~fresh).sum())
        return self.store.add(segment, keep=fresh)

    def ready(self) -> bool:
        """More than ``buffer_size`` steps, as ML-Agents' trainers wait for."""
        return self.buffered() > self.settings.hyperparameters.buffer_size

    def wanted(self) -> int | None:
        return on_policy_wanted(self.settings.hyperparameters.buffer_size, self.buffered())

    def buffered(self) -> int:
        """The steps that count towards ``buffer_size``."""
        return self.store.train_steps

    # --- the update ---------------------------------------------------------------------

    def update(self, progress: float) -> dict[str, float]:
        """One iteration on everything stored; ``progress`` in [0, 1] drives schedules. The
        variants change its parts (what is normalized, the estimates, the loss's targets,
        the report), not its order."""
        rows = self.store.take()
        train = rows.train.nonzero().squeeze(-1)  # the steps that count in the loss
        self.update_normalization(rows, None if len(train) == len(rows) else train)
        with torch.no_grad():
            value, advantage, targets = self.estimates(rows)
        advantage = self.normalized(advantage, train)

        lr, epsilon, beta = self.schedules(progress)
        self.step.start(self._bind(advantage, *targets), epsilon, beta)
        signals = self.train_beside(train)
        mean = self.step.means()
        return {
            **signals,
            **actor_critic_report(mean, lr, beta),
            **self.estimate_report(value, targets, train, mean),
            "Policy/Epsilon": epsilon,
            "Policy/Clip Fraction": mean.get("clip_fraction", 0.0),
            "Policy/Approx KL": mean.get("kl_approx", 0.0),
            "Policy/Stale Steps Dropped": float(self.stale_steps),
            "Policy/Samples": float(len(train)),
        }

    def update_normalization(self, rows: Rows, subset: torch.Tensor | None) -> None:
        """The running observation statistics, from the rows that train (``subset``; all
        when None)."""
        self.network.update_normalization(rows.obs, subset)

    def estimates(self, rows: Rows) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, ...]]:
        """(value, advantage, the loss's targets besides the advantage) per row."""
        value, advantage, value_target = self.estimate(rows)
        return value, advantage, (value_target,)

    def estimate_report(
        self,
        value: torch.Tensor,
        targets: tuple[torch.Tensor, ...],
        train: torch.Tensor,
        mean: dict[str, float],
    ) -> dict[str, float]:
        """ML-Agents' value estimates of the update, the reward signals' included."""
        extrinsic = value[train].reshape(len(train), -1)[:, 0]
        return {
            **self.signals.report(value, train),
            "Policy/Extrinsic Value Estimate": float(extrinsic.mean()),
        }

    def normalized(self, advantage: torch.Tensor, train: torch.Tensor) -> torch.Tensor:
        """The advantages normalized over the steps that train, with numpy's std (no
        Bessel correction), as ML-Agents' ``_update_policy`` does over its buffer."""
        trained = advantage[train]
        return (advantage - trained.mean()) / (trained.std(correction=0) + 1e-10)

    def train_beside(self, train: torch.Tensor) -> dict[str, float]:
        """PPO's epochs, and the reward signals' networks trained beside them: on a CPU
        in a thread of their own (their networks share nothing with the policy's, and
        their steps release the GIL), from a generator seeded from the global one first,
        so that a seed still gives one run. On a GPU (a CUDA graph's capture may not
        meet another thread's work) one after the other. Returns the signals' losses."""
        h = self.settings.hyperparameters
        if not self.signals.items or self.compute.torch_device.type != "cpu":
            self.epochs(train)
            return self.signals.train(train, h.num_epoch, h.batch_size)
        generator = torch.Generator().manual_seed(int(torch.randint(2**62, ())))
        with ThreadPoolExecutor(1, thread_name_prefix="signals") as beside:
            losses = beside.submit(self.signals.train, train, h.num_epoch, h.batch_size, generator)
            self.epochs(train)
            return losses.result()

    def schedules(self, progress: float) -> tuple[float, float, float]:
        """This update's learning rate (set in the optimizer), epsilon and beta."""
        h = self.settings.hyperparameters
        schedule = h.learning_rate_schedule
        lr = decay(h.learning_rate, progress, schedule)
        epsilon = decay(h.epsilon, progress, h.epsilon_schedule or schedule, EPSILON_END)
        beta = decay(h.beta, progress, h.beta_schedule or schedule, BETA_END)
        set_learning_rate(self.optimizer, lr)
        return lr, epsilon, beta

    def epochs(self, train: torch.Tensor) -> None:
        """``num_epoch`` passes of shuffled minibatches of the ``train`` rows (the
        remainder left out, as ML-Agents does)."""
        h = self.settings.hyperparameters
        for _ in range(h.num_epoch):
            order = train[torch.randperm(len(train), device=train.device)]
            for index in order.split(h.batch_size):
                if len(index) == h.batch_size:
                    self.step(index)

    def _bind(self, advantage: torch.Tensor, value_target: torch.Tensor) -> tuple[int, ...]:
        """Point ``self._bound`` at the store's whole columns, with this update's advantages
        and targets copied into buffers beside them; returns the addresses a graph reads."""
        whole, heads = self.store.whole(), 1 + len(self.signals)
        if self._targets is None or self._targets.shape[1] != len(whole):
            shape = (1 + heads, len(whole))
            self._targets = torch.zeros(shape, device=self.compute.torch_device)
        self._targets[0, : len(advantage)] = advantage
        self._targets[1:, : len(value_target)] = value_target.reshape(len(value_target), -1).T
        targets = self._targets[1] if heads == 1 else self._targets[1:].T  # [N] or [N, heads]
        self._bound = Steps.of(whole, self._targets[0], targets)
        fields = (*whole.obs.values(), whole.continuous, whole.discrete, whole.mask)
        tensors = [t for t in (*fields, whole.log_prob, self._targets) if t is not None]
        return tuple(t.data_ptr() for t in tensors)

    def _minibatch_loss(
        self, index: torch.Tensor, scalars: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        assert self._bound is not None
        return self.loss(self._bound[index], scalars[0], scalars[1])

    def estimate(self, rows: Rows) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(value, advantage, value target) per row: GAE along each packed trajectory
        (torchrl's vectorized estimator), which stops at ``done`` and bootstraps from the
        next observation unless ``terminated``; a step's next value is the next row's,
        except at a truncated end, where it is its kept next observation's."""
        value, next_value = self.value_estimates(rows)
        advantage, targets = torch.zeros_like(value[:, 0]), []
        extrinsic = (rows.reward * self.settings.reward_strength, self.settings.gamma, False)
        signals = self.signals.rewards(rows)  # after the extrinsic one
        for k, (reward, gamma, ignore_done) in enumerate([extrinsic, *signals]):
            # curiosity and rnd bootstrap at an episode's end (ML-Agents' ignore_done)
            terminated = torch.zeros_like(rows.terminated) if ignore_done else rows.terminated
            gained, target = self.gae(
                rows, value[:, k], next_value[:, k], reward, gamma, terminated
            )
            advantage += gained  # ML-Agents sums the signals' advantages
            targets.append(target)
        if len(targets) == 1:  # the extrinsic signal alone: [N] each
            return value[:, 0], advantage, targets[0]
        return value, advantage, torch.stack(targets, dim=-1)

    def value_estimates(self, rows: Rows) -> tuple[torch.Tensor, torch.Tensor]:
        """V of each row and of what follows it ``[N, 1 + intrinsic signals]`` each: the
        next row's, or at a truncated end its kept next observation's."""
        value = self.values(rows.obs)
        next_value = torch.zeros_like(value)
        next_value[:-1] = value[1:]
        next_value[rows.end_rows] = self.values(rows.end_obs)
        return value, next_value

    def gae(
        self,
        rows: Rows,
        value: torch.Tensor,
        next_value: torch.Tensor,
        reward: torch.Tensor,
        gamma: float | None = None,
        terminated: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """torchrl's vectorized GAE along the packed trajectories: (advantage, target);
        the extrinsic signal's gamma and ends unless given."""
        terminated = rows.terminated if terminated is None else terminated
        advantage, target = vec_generalized_advantage_estimate(
            self.settings.gamma if gamma is None else gamma,
            self.settings.hyperparameters.lambd,
            value.unsqueeze(-1),
            next_value.unsqueeze(-1),
            reward.unsqueeze(-1),
            rows.done.unsqueeze(-1),
            terminated.unsqueeze(-1),
            time_dim=-2,
        )
        return advantage.squeeze(-1), target.squeeze(-1)

    def values(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """V of many rows, ``[N, 1 + intrinsic signals]``, in chunks of about
        ``VALUE_CHUNK_BYTES`` of float input, so a large observation is never converted
        whole."""
        rows, chunk = len(next(iter(obs.values()))), value_chunk(obs)
        heads = self.signals.heads
        parts = [
            self.network.value_of(
                self.network.encode({n: o[i : i + chunk] for n, o in obs.items()}, critic=True),
                heads,
            )
            for i in range(0, rows, chunk)
        ]
        if not parts:
            return torch.zeros(0, 1 + len(heads), device=self.compute.torch_device)
        return torch.cat(parts).reshape(rows, -1)  # [N, 1 + intrinsic signals]

    def loss(
        self, steps: Steps, epsilon: float | torch.Tensor, beta: float | torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """ML-Agents' PPO loss on a minibatch: per-component clipped surrogate, squared
        value error (weight 0.5), entropy bonus (weight ``beta``); epsilon and beta may be
        0-dim tensors (a CUDA graph reads them there)."""
        log_prob, entropy, value = self.network.evaluate(
            steps.obs, steps.continuous, steps.discrete, steps.mask, self.signals.heads
        )
        terms = policy_terms(log_prob, entropy, steps, epsilon, beta)
        value_loss = (steps.value_target - value).square()
        # summed for the gradient in this order: objective, critic, entropy
        return {
            "loss_objective": terms.pop("loss_objective"),
            "loss_critic": 0.5 * value_loss.mean(),
        } | terms

    # --- checkpoints --------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        optimizer = plain_learning_rates(self.optimizer.state_dict())
        state = {"optimizer": optimizer, "stale_steps": self.stale_steps}
        return state | ({"signals": self.signals.state_dict()} if self.signals else {})

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if self.signals:
            self.signals.load_state_dict(state["signals"])
        load_optimizer(self.optimizer, state["optimizer"])
        self.step.drop_graph()
        self.stale_steps = int(state.get("stale_steps", 0))
