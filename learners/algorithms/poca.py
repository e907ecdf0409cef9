"""POCA for one behavior's groups, as mlagents-learn 1.1.0 runs it (``trainer_type: poca``).

MA-POCA (Cohen et al., 2021) is PPO with a centralized critic that attends over however
many agents a group has (``learners/networks/group_critic.py``). Read top to bottom, one update:

- segments arrive with each step's groupmates (``rollout.collecting.groups``) and are stored with
  them (``TrajectoryStore(groupmates=True)``) until more than ``buffer_size`` steps are
  there, as PPO's;
- the agents' own observations update the policy's and the critic's normalization;
- the reward of a step is the agent's own, its group's, and its groupmates' of the same
  exchange (ML-Agents' extrinsic signal under POCA, ``add_groupmate_rewards``;
  ``learners/reward_signals/extrinsic.py``), times ``strength``;
- V is the critic's value of the agent with its groupmates; the lambda-return runs along
  each trajectory on V (torchrl's GAE target is the same number), bootstrapping at its end
  from the group's next observations unless the agent's episode and every groupmate's
  ended: an agent that leaves mid-episode (DungeonEscape's sacrifice) still gets the
  value of what its group goes on to earn;
- the advantage is the lambda-return minus the agent's counterfactual baseline (its
  groupmates' actions given, its own left out), normalized over the buffer;
- ``num_epoch`` passes of shuffled minibatches: PPO's clipped surrogate per action
  component, and the value and the baseline regressed on the lambda-return, weighed
  ``policy + 0.5 (value + 0.5 baseline) - beta entropy``. The baseline's loss is clipped
  to ``epsilon`` around its estimate before the update (ML-Agents' trust-region value
  loss); the value's is the plain squared error, which is what mlagents-learn 1.1.0
  computes in effect, as for PPO: the old estimate its clip reads is the return (its
  ``value_estimates_key`` names the returns' field), so that clip never binds.
  ``benchmarks/equality/check_poca_vs_mlagents.py`` checks one update against its code.

Schedules, policy lag, the optimizer and checkpoints are PPO's (``learners/algorithms/ppo.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from learners.algorithms.minibatch import REPORTED
from learners.algorithms.ppo import PPO, Steps, policy_terms, value_chunk
from learners.algorithms.trajectory_store import Rows
from learners.host.devices import Compute
from learners.networks.group_critic import GroupCritic

if TYPE_CHECKING:
    from learners.networks.policies import ActorCritic
    from learners.trainer_config.settings import TrainerSettings


@dataclass(frozen=True)
class GroupSteps:
    """PPO's steps with their groupmates and the baselines the baseline loss clips around."""

    steps: Steps  # value_target: the lambda-return
    mates: dict[str, torch.Tensor]  # sensor -> [N, M, ...]
    mate_continuous: torch.Tensor | None  # [N, M, c]
    mate_discrete: torch.Tensor | None  # [N, M, branches]
    present: torch.Tensor  # [N, M] bool
    old_baseline: torch.Tensor  # [N]

    def __getitem__(self, index: torch.Tensor) -> GroupSteps:
        def pick(tensor: torch.Tensor | None) -> torch.Tensor | None:
            return None if tensor is None else tensor[index]

        return GroupSteps(
            self.steps[index],
            {name: obs[index] for name, obs in self.mates.items()},
            pick(self.mate_continuous),
            pick(self.mate_discrete),
            self.present[index],
            self.old_baseline[index],
        )


def trust_region_loss(
    new: torch.Tensor, old: torch.Tensor, target: torch.Tensor, epsilon: float | torch.Tensor
) -> torch.Tensor:
    """ML-Agents' clipped value loss: the worse of the estimate's and of the estimate
    clipped to ``epsilon`` around the old one."""
    clipped = old + (new - old).clamp(-epsilon, epsilon)
    return torch.max((target - new).square(), (target - clipped).square()).mean()


class POCA(PPO):
    groupmates = True
    reported = (*REPORTED, "loss_baseline")

    def __init__(
        self, network: ActorCritic, settings: TrainerSettings, compute: Compute | None = None
    ) -> None:
        compute = compute or Compute()
        self.critic = GroupCritic(network.spec, network.settings)
        compute.place(self.critic)
        super().__init__(network, settings, compute)
        self._group_bound: GroupSteps | None = None

    def trained_parameters(self) -> list[torch.nn.Parameter]:
        return [*self.network.parameters(), *self.critic.parameters()]

    # --- the update ---------------------------------------------------------------------

    def update_normalization(self, rows: Rows, subset: torch.Tensor | None) -> None:
        super().update_normalization(rows, subset)
        own = rows.obs if subset is None else {n: o[subset] for n, o in rows.obs.items()}
        self.critic.update_normalization(own)

    def estimates(self, rows: Rows) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, ...]]:
        """The group critic's: advantage = lambda-return - baseline; the targets are the
        lambda-return (of V) and the baseline's."""
        value, baseline, returns = self.estimate_group(rows)
        return value, returns - baseline, (returns, baseline)

    def estimate_report(
        self,
        value: torch.Tensor,
        targets: tuple[torch.Tensor, ...],
        train: torch.Tensor,
        mean: dict[str, float],
    ) -> dict[str, float]:
        baseline = targets[1]
        return {
            "Losses/Baseline Loss": mean["loss_baseline"] * 4,  # undo 0.5 * 0.5
            "Policy/Extrinsic Value Estimate": float(value[train].mean()),
            "Policy/Extrinsic Baseline Estimate": float(baseline[train].mean()),
        }

    def estimate_group(self, rows: Rows) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(V, baseline, lambda-return) per row."""
        g, e = rows.groupmates, rows.end_groupmates
        mates = {k[4:]: v for k, v in g.items() if k.startswith("obs/")}
        action = self.critic.flat_action(g.get("continuous"), g.get("discrete"))
        present = g["present"]

        def value(s: slice) -> torch.Tensor:
            own = {n: o[s] for n, o in rows.obs.items()}
            return self.critic.value(own, {n: m[s] for n, m in mates.items()}, present[s])

        def baseline(s: slice) -> torch.Tensor:
            own = {n: o[s] for n, o in rows.obs.items()}
            others = {n: m[s] for n, m in mates.items()}
            return self.critic.baseline(own, others, action[s], present[s])

        width = 1 + present.shape[1]
        values = self._chunked(value, rows, width)
        baselines = self._chunked(baseline, rows, width)
        next_value = torch.zeros_like(values)
        next_value[:-1] = values[1:]
        if len(rows.end_rows):
            end_mates = {k[4:]: v for k, v in e.items() if k.startswith("obs/")}
            end_value = self.critic.value(rows.end_obs, end_mates, e["present"])
            next_value[rows.end_rows] = end_value
        mates_reward = (g["reward"] * present).sum(-1)
        reward = (rows.reward + mates_reward) * self.settings.reward_strength
        _, returns = self.gae(rows, values, next_value, reward)
        return values, baselines, returns

    def _chunked(
        self, fn: Callable[[slice], torch.Tensor], rows: Rows, entities: int
    ) -> torch.Tensor:
        """``fn`` over slices of the rows, about ``VALUE_CHUNK_BYTES`` of float input each."""
        chunk = value_chunk(rows.obs, entities)
        parts = [fn(slice(i, i + chunk)) for i in range(0, len(rows), chunk)]
        return torch.cat(parts) if parts else torch.zeros(0, device=self.compute.torch_device)

    def _bind(self, *targets: torch.Tensor) -> tuple[int, ...]:
        """As PPO's ``_bind``: the store's whole columns, with this update's advantage,
        lambda-return and baseline in buffers beside them (a CUDA graph reads them)."""
        whole = self.store.whole()
        if self._targets is None or self._targets.shape[1] != len(whole):
            self._targets = torch.zeros(3, len(whole), device=self.compute.torch_device)
        for row, values in enumerate(targets):
            self._targets[row, : len(values)] = values
        g = whole.groupmates
        self._group_bound = GroupSteps(
            Steps.of(whole, self._targets[0], self._targets[1]),
            {k[4:]: v for k, v in g.items() if k.startswith("obs/")},
            g.get("continuous"),
            g.get("discrete"),
            g["present"],
            self._targets[2],
        )
        fields = (*whole.obs.values(), whole.continuous, whole.discrete, whole.mask)
        tensors = [
            t for t in (*fields, whole.log_prob, *g.values(), self._targets) if t is not None
        ]
        return tuple(t.data_ptr() for t in tensors)

    def _minibatch_loss(
        self, index: torch.Tensor, scalars: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        assert self._group_bound is not None
        return self.group_loss(self._group_bound[index], scalars[0], scalars[1])

    def group_loss(
        self, batch: GroupSteps, epsilon: float | torch.Tensor, beta: float | torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """ML-Agents' POCA loss on a minibatch."""
        steps = batch.steps
        log_prob, entropy, _ = self.network.evaluate(
            steps.obs, steps.continuous, steps.discrete, steps.mask
        )
        terms = policy_terms(log_prob, entropy, steps, epsilon, beta)
        value = self.critic.value(steps.obs, batch.mates, batch.present)
        action = self.critic.flat_action(batch.mate_continuous, batch.mate_discrete)
        baseline = self.critic.baseline(steps.obs, batch.mates, action, batch.present)
        returns = steps.value_target
        value_loss = (returns - value).square().mean()
        baseline_loss = trust_region_loss(baseline, batch.old_baseline, returns, epsilon)
        return {
            "loss_objective": terms.pop("loss_objective"),
            "loss_critic": 0.5 * value_loss,
            "loss_baseline": 0.25 * baseline_loss,
        } | terms

    # --- checkpoints --------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "critic": self.critic.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.critic.load_state_dict(state["critic"])
        super().load_state_dict(state)
