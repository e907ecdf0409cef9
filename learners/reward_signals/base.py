"""What every reward signal besides the extrinsic one shares
(``learners/reward_signals/intrinsic.py``'s curiosity and RND, ``learners/reward_signals/gail.py``):
the steps it reads, the body its networks are built on (ML-Agents' ``NetworkBody``: encoders and MLP
of the signal's own ``network_settings``, initialized as ML-Agents initializes them), and its
interface."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from mlagents_envs.base_env import BehaviorSpec
from torch import nn

from learners.networks.policies import ActorCritic
from learners.trainer_config.settings import NetworkSettings, RewardSignalSettings

EPSILON = 1e-10


@dataclass(frozen=True)
class Transitions:
    """What a signal reads of some steps: observations, the next ones, the actions."""

    obs: dict[str, torch.Tensor]
    next_obs: dict[str, torch.Tensor]
    continuous: torch.Tensor | None  # as stored: the Gaussian's sample
    discrete: torch.Tensor | None
    done: torch.Tensor | None = None  # the step ended its episode (gail's use_actions)

    def __getitem__(self, index: torch.Tensor) -> Transitions:
        def pick(tensor: torch.Tensor | None) -> torch.Tensor | None:
            return None if tensor is None else tensor[index]

        return Transitions(
            {n: o[index] for n, o in self.obs.items()},
            {n: o[index] for n, o in self.next_obs.items()},
            pick(self.continuous),
            pick(self.discrete),
            pick(self.done),
        )


class NetworkBody(nn.Module):
    """Encoders and MLP of ``settings``: ML-Agents' ``NetworkBody`` (features only; the
    heads and critic of the ``ActorCritic`` it is built as stay unused)."""

    def __init__(self, spec: BehaviorSpec, settings: NetworkSettings) -> None:
        super().__init__()
        self.network = ActorCritic(spec, settings)
        self.width = settings.hidden_units

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.network.features(obs)

    def trained(self) -> list[nn.Parameter]:
        return [*self.network.encoders.parameters(), *self.network.trunk.parameters()]

    def update_normalization(self, obs: dict[str, torch.Tensor]) -> None:
        self.network.update_normalization(obs)


class Signal(nn.Module):
    """What PPO needs of a signal; ``stat`` is ML-Agents' name in its TensorBoard tags."""

    stat = ""
    ignore_done = True  # its value bootstraps at an episode's end (ML-Agents' ignore_done)
    reads_next_obs = False  # its networks see a step's next observation

    def __init__(self, settings: RewardSignalSettings) -> None:
        super().__init__()
        self.settings = settings
        self.gamma, self.strength = settings.gamma, settings.strength

    def rewards(self, steps: Transitions) -> torch.Tensor:
        raise NotImplementedError

    def update(
        self, steps: Transitions, generator: torch.Generator | None = None
    ) -> dict[str, float]:
        """One training step on ``steps``; its random draws from ``generator`` (None: the
        global one), so that it can train beside PPO's epochs in a thread of its own."""
        raise NotImplementedError

    def update_normalization(self, steps: Transitions) -> None:
        raise NotImplementedError

    def _step(self, loss: torch.Tensor) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()


def flat_actions(steps: Transitions, continuous: int, branches: tuple[int, ...]) -> torch.Tensor:
    """The continuous action, then each branch's choice one-hot (ML-Agents' flattener)."""
    parts = []
    if continuous:
        assert steps.continuous is not None
        parts.append(steps.continuous)
    if branches:
        assert steps.discrete is not None
        parts += [
            nn.functional.one_hot(steps.discrete[:, i], size).float()
            for i, size in enumerate(branches)
        ]
    return torch.cat(parts, dim=-1)
