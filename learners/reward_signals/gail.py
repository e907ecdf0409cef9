"""GAIL: a discriminator tells the expert's recorded steps from the policy's, and its
belief that a step is the expert's becomes a reward, as ML-Agents' GAIL provider does it.

- The discriminator: the encoders and MLP of the signal's ``network_settings`` (with
  ``use_actions``, the flattened action and the episode-end flag enter the MLP beside the
  encoded observations), then one sigmoid unit. With ``use_vail``, a variational
  bottleneck of 128 units sits before that unit, its weight ``beta`` adjusted towards a
  mutual information of 0.5 (ML-Agents' VAIL).
- The reward of a step: ``-log(1 - D(step))``. GAIL stops at an episode's end, as the
  extrinsic signal does.
- One update per minibatch of PPO's: as many expert steps drawn at random, the loss
  ``-log D(expert) - log(1 - D(policy))``, plus 10 x a gradient penalty on points between
  the two (the gradient with respect to the first sensor, as ML-Agents takes it).

The episode-end flag of the policy's steps is ``terminated``: an end at ``max_step``
looks like a horizon cut in our rows (ML-Agents counts it as an end too).
"""

from __future__ import annotations

import torch
from mlagents_envs.base_env import BehaviorSpec
from torch import nn

from batches.expert_steps import ExpertSteps
from learners.acting.numpy_policy import trunk_input_width
from learners.networks.initializers import kaiming, xavier
from learners.networks.policies import ActorCritic
from learners.reward_signals.base import Signal, Transitions, flat_actions
from learners.trainer_config.settings import RewardSignalSettings

Z_SIZE, ALPHA, MUTUAL_INFORMATION = 128, 0.0005, 0.5
GRADIENT_PENALTY, EPSILON = 10.0, 1e-7


class Discriminator(nn.Module):
    def __init__(self, spec: BehaviorSpec, settings: RewardSignalSettings) -> None:
        super().__init__()
        net = settings.network_settings
        self.network = ActorCritic(spec, net)  # its encoders only: ``encode``
        self.continuous = spec.action_spec.continuous_size
        self.branches = tuple(spec.action_spec.discrete_branches)
        self.use_actions, self.use_vail = settings.use_actions, settings.use_vail
        extra = self.continuous + sum(self.branches) + 1 if self.use_actions else 0
        width, layers = trunk_input_width(spec, net) + extra, []
        for _ in range(net.num_layers):
            layers += [kaiming(width, net.hidden_units), nn.SiLU()]
            width = net.hidden_units
        self.body = nn.Sequential(*layers)
        if self.use_vail:
            self.z_sigma = nn.Parameter(torch.ones(Z_SIZE))
            self.z_mu = kaiming(width, Z_SIZE, gain=0.1)
            self.beta = nn.Parameter(torch.zeros(()), requires_grad=False)
            width = Z_SIZE
        self.estimator = nn.Sequential(xavier(width, 1, gain=0.2), nn.Sigmoid())

    def inputs(self, steps: Transitions) -> list[torch.Tensor]:
        """Each sensor's observation, then (``use_actions``) the actions and end flags."""
        obs = [steps.obs[name] for name in self.network.sensor_names]
        if not self.use_actions:
            return obs
        assert steps.done is not None
        actions = flat_actions(steps, self.continuous, self.branches)
        return [*obs, torch.cat([actions, steps.done.float().unsqueeze(-1)], dim=-1)]

    def estimate(
        self, inputs: list[torch.Tensor], noise: bool, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """D of each step, and the bottleneck's mean (``use_vail``; sampled around it with
        ``noise``, from ``generator``)."""
        names = self.network.sensor_names
        encoded = self.network.encode(dict(zip(names, inputs[: len(names)], strict=True)))
        hidden = self.body(torch.cat([encoded, *inputs[len(names) :]], dim=-1))
        mu = None
        if self.use_vail:
            mu = self.z_mu(hidden)
            hidden = mu
            if noise:
                draw = torch.randn(mu.shape, generator=generator, device=mu.device)
                hidden = mu + draw * self.z_sigma
        return self.estimator(hidden).squeeze(-1), mu


class GAIL(Signal):
    stat = "Gail"
    ignore_done = False

    def __init__(
        self, spec: BehaviorSpec, settings: RewardSignalSettings, experts: ExpertSteps
    ) -> None:
        super().__init__(settings)
        self.discriminator = Discriminator(spec, settings)
        self.experts = experts
        self.optimizer = torch.optim.Adam(
            self.discriminator.parameters(), settings.learning_rate, fused=True
        )
        self._expert: Transitions | None = None  # the demonstrations on this module's device

    def rewards(self, steps: Transitions) -> torch.Tensor:
        with torch.no_grad():
            d, _ = self.discriminator.estimate(self.discriminator.inputs(steps), noise=False)
        return -torch.log(1.0 - d * (1.0 - EPSILON))

    def update_normalization(self, steps: Transitions) -> None:
        self.discriminator.network.update_normalization(steps.obs)

    def update(
        self, steps: Transitions, generator: torch.Generator | None = None
    ) -> dict[str, float]:
        expert = self._expert_sample(len(next(iter(steps.obs.values()))), generator)
        self.discriminator.network.update_normalization(expert.obs)
        disc = self.discriminator
        policy_in, expert_in = disc.inputs(steps), disc.inputs(expert)
        policy_d, policy_mu = disc.estimate(policy_in, noise=True, generator=generator)
        expert_d, expert_mu = disc.estimate(expert_in, noise=True, generator=generator)
        loss = -(torch.log(expert_d + EPSILON) + torch.log(1.0 - policy_d + EPSILON)).mean()
        stats = {
            "Policy/GAIL Policy Estimate": float(policy_d.detach().mean()),
            "Policy/GAIL Expert Estimate": float(expert_d.detach().mean()),
            "Losses/GAIL Loss": float(loss.detach()),
        }
        total = loss
        if disc.use_vail:
            assert policy_mu is not None and expert_mu is not None
            var = disc.z_sigma.square()
            kl = (-(1 + var.log() - 0.5 * expert_mu**2 - 0.5 * policy_mu**2 - var).sum(-1)).mean()
            total = total + disc.beta * (kl - MUTUAL_INFORMATION)
            stats["Losses/GAIL KL Loss"] = float(kl.detach())
        penalty = GRADIENT_PENALTY * self._gradient_penalty(policy_in, expert_in, generator)
        stats["Policy/GAIL Grad Mag Loss"] = float(penalty.detach())
        self._step(total + penalty)
        if disc.use_vail:  # dual ascent on beta (ML-Agents: with the loss this step used)
            with torch.no_grad():
                step = ALPHA * (stats["Losses/GAIL KL Loss"] - MUTUAL_INFORMATION)
                disc.beta.copy_((disc.beta + step).clamp(min=0.0))
            stats["Policy/GAIL Beta"] = float(disc.beta)
        return stats

    def _gradient_penalty(
        self,
        policy_in: list[torch.Tensor],
        expert_in: list[torch.Tensor],
        generator: torch.Generator | None,
    ) -> torch.Tensor:
        """(|dD/dx| - 1)^2 at random points between policy and expert inputs; the
        gradient with respect to the first input, as ML-Agents takes it."""
        mixed = []
        for policy, expert in zip(policy_in, expert_in, strict=True):
            share = torch.rand(policy.shape, generator=generator, device=policy.device)
            point = share * policy.float() + (1 - share) * expert.float()
            mixed.append(point.requires_grad_(True))
        estimate, _ = self.discriminator.estimate(mixed, noise=True, generator=generator)
        (gradient,) = torch.autograd.grad(estimate.sum(), mixed[0], create_graph=True)
        norm = (gradient.flatten(1).square().sum(-1) + EPSILON).sqrt()
        return (norm - 1).square().mean()

    def _expert_sample(self, count: int, generator: torch.Generator | None) -> Transitions:
        device = next(self.parameters()).device
        if self._expert is None:
            e, names = self.experts, self.discriminator.network.sensor_names
            obs = {
                n: torch.as_tensor(o, device=device)
                for n, o in zip(names, e.observations, strict=True)
            }
            self._expert = Transitions(
                obs,
                obs,
                torch.as_tensor(e.continuous, device=device),
                torch.as_tensor(e.discrete, device=device),
                torch.as_tensor(e.done, device=device),
            )
        index = torch.randint(len(self.experts), (count,), generator=generator, device=device)
        return self._expert[index]
