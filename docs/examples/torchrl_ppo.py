"""PPO on 3DBall with torchrl's own pieces, over ``UnityCollector``: the loop of torchrl's
PPO examples with only the environment changed (docs/torchrl.md).

    .venv/bin/python docs/examples/torchrl_ppo.py --frames 300000

Each batch: GAE over the batch as it comes (rows end ``done``, cut or finished), into a
replay buffer sampled without replacement for a few epochs of ``ClipPPOLoss``, then the
actor's new weights to every worker.
"""

from __future__ import annotations

import argparse
from typing import Any

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from torchrl_adapters import UnityCollector


def mlp(inputs: int, outputs: int, width: int = 128) -> nn.Sequential:
    layers = [nn.Linear(inputs, width), nn.SiLU(), nn.Linear(width, width), nn.SiLU()]
    return nn.Sequential(*layers, nn.Linear(width, outputs))


def make_actor_critic(observations: int, actions: int) -> tuple[ProbabilisticActor, ValueOperator]:
    net = nn.Sequential(mlp(observations, 2 * actions), NormalParamExtractor())
    actor = ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        return_log_prob=True,
    )
    critic = ValueOperator(mlp(observations, 1), in_keys=["observation"])
    return actor, critic


def train(
    build: str = "unitysim:3DBall",
    behavior: str = "3DBall",
    total_frames: int = 300_000,
    frames_per_batch: int = 4096,
    minibatch: int = 512,
    epochs: int = 3,
    learning_rate: float = 3e-4,
    observations: int = 8,
    actions: int = 2,
    **collector_options: Any,
) -> list[dict[str, float]]:
    """Returns, per batch: the mean reward per step, the episodes ended, the loss."""
    torch.manual_seed(0)
    actor, critic = make_actor_critic(observations, actions)
    loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_coeff=0.005)
    advantage = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=True)
    optimizer = torch.optim.Adam(loss.parameters(), lr=learning_rate)
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(frames_per_batch),
        sampler=SamplerWithoutReplacement(),
        batch_size=minibatch,
    )
    history = []
    with UnityCollector(
        build, actor, frames_per_batch, total_frames, behavior=behavior, **collector_options
    ) as collector:
        for batch in collector:
            with torch.no_grad():
                advantage(batch)
            buffer.extend(batch)
            for _ in range(epochs * (frames_per_batch // minibatch)):
                losses = loss(buffer.sample())
                total = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
                optimizer.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 0.5)
                optimizer.step()
            collector.update_policy_weights_()
            history.append(
                {
                    "reward": batch["next", "reward"].mean().item(),
                    "episodes": int(batch["next", "terminated"].sum()),
                    "loss": total.item(),
                    "policy_version": int(batch["policy_version"].max()),
                }
            )
            print(f"frames {collector.frames:,}: {history[-1]}", flush=True)
    return history


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="unitysim:3DBall")
    parser.add_argument("--frames", type=int, default=300_000)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    train(args.env, total_frames=args.frames, num_workers=args.workers)
