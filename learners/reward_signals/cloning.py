"""Behavioral cloning beside PPO, POCA or SAC, as ML-Agents' BC module trains it.

After each update of its behavior, ``num_epoch`` passes (3 unless set) over shuffled
minibatches of ``batch_size`` demonstration steps (``samples_per_update`` of them per
pass, 0: all; the remainder left out), each one Adam step of its own on the policy's
parameters (encoders, policy trunk and heads; not the critic's) at ``learning_rate x
strength``. With ``steps`` > 0 that rate decays linearly to 1e-10 over the behavior's
first ``steps`` steps, and cloning stops there; the rate an update uses is the one the
update before it set, as in ML-Agents.

The loss per minibatch:
- continuous actions: the mean squared error between the policy's sampled action (the
  Gaussian's reparameterized sample) and the expert's. ML-Agents 1.1.0 compares the raw
  sample, which Unity receives clipped to [-3, 3] and divided by 3, with the expert's
  action in [-1, 1]; here the sample is taken as Unity receives it, so a cloned policy
  sends the expert's action and not a third of it;
- discrete actions: each branch's cross-entropy with the expert's choice (every action
  allowed), averaged over branches and steps.
"""

from __future__ import annotations

import torch

from batches.expert_steps import ExpertSteps
from learners.algorithms.minibatch import set_learning_rate
from learners.algorithms.schedules import LR_END, decay
from learners.networks.policies import ActorCritic
from learners.trainer_config.settings import BehavioralCloningSettings, Hyperparameters

CRITIC = ("critic_trunk.", "critic_lstm.", "value.")  # parameters cloning leaves alone
NUM_EPOCH = 3  # ML-Agents' BC module's own default, not hyperparameters.num_epoch
REPORT = "Losses/Pretraining Loss"  # ML-Agents' TensorBoard tag


class BehavioralCloning:
    def __init__(
        self,
        network: ActorCritic,
        settings: BehavioralCloningSettings,
        hyperparameters: Hyperparameters,
        experts: ExpertSteps,
        device: torch.device | str = "cpu",
    ) -> None:
        self.network, self.settings = network, settings
        self.initial_lr = hyperparameters.learning_rate * settings.strength
        self.lr = self.initial_lr
        self.batch_size = min(settings.batch_size or hyperparameters.batch_size, len(experts))
        self.num_epoch = settings.num_epoch or NUM_EPOCH
        names = network.sensor_names
        self.obs = {
            name: torch.as_tensor(values, device=device)
            for name, values in zip(names, experts.observations, strict=True)
        }
        self.continuous = torch.as_tensor(experts.continuous, device=device)
        self.discrete = torch.as_tensor(experts.discrete, device=device)
        self.size = len(experts)
        memory = network.settings.memory
        # with memory: minibatches of whole sequences, run from zero memories (ML-Agents')
        self.length = memory.sequence_length if memory is not None else 1
        policy = [p for n, p in network.named_parameters() if not n.startswith(CRITIC)]
        self.optimizer = torch.optim.Adam(policy, lr=self.initial_lr, fused=True)

    def learning_rate(self, steps: int) -> float:
        """The rate after the behavior's ``steps``: linear to 1e-10 over ``steps`` steps."""
        anneal = self.settings.steps
        if anneal <= 0:
            return self.initial_lr
        return decay(self.initial_lr, steps / anneal, "linear", LR_END)

    def update(self, steps: int) -> dict[str, float]:
        """One round of cloning after an update at the behavior's ``steps``."""
        next_lr = self.learning_rate(steps)
        if self.lr <= LR_END:
            return {REPORT: 0.0}
        batches = self.size // self.batch_size
        if self.settings.samples_per_update:
            batches = min(batches, self.settings.samples_per_update // self.batch_size)
        per_batch = max(1, self.batch_size // self.length)  # sequences (steps without memory)
        starts = max(1, self.size // self.length)
        losses = []
        for _ in range(self.num_epoch):
            order = torch.randperm(starts, device=self.continuous.device) * self.length
            for i in range(min(batches, starts // per_batch)):
                index = order[i * per_batch : (i + 1) * per_batch]
                loss = self.loss(index)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                self.optimizer.step()
                losses.append(loss.detach())
        set_learning_rate(self.optimizer, next_lr)
        self.lr = next_lr
        return {REPORT: float(torch.stack(losses).mean()) if losses else 0.0}

    def loss(self, index: torch.Tensor) -> torch.Tensor:
        """The loss on the demonstration steps at ``index`` (with memory: the sequences of
        ``sequence_length`` steps starting there, each from zero memory)."""
        network = self.network
        if network.lstm is not None:
            places = index.unsqueeze(-1) + torch.arange(self.length, device=index.device)
            places = places.clamp(max=self.size - 1)
            index = places.flatten()
        hidden = network.features({name: obs[index] for name, obs in self.obs.items()})
        if network.lstm is not None:
            sequences = hidden.unflatten(0, places.shape)
            hidden = network.recur(network.lstm, sequences, None)[0].flatten(0, 1)
        loss = torch.zeros((), device=hidden.device)
        if network.mean is not None:
            mean, log_std = network.mean_log_std(hidden)
            sample = mean + torch.randn_like(mean) * log_std.exp()
            if network.settings.tanh_squash:
                sample = torch.tanh(sample)
            sent = network.unity_action(sample)
            loss = loss + torch.nn.functional.mse_loss(sent, self.continuous[index])
        if network.logits is not None:
            logits, offset, entropies = network.logits(hidden), 0, []
            for branch, size in enumerate(network.branches):
                log_p = torch.log_softmax(logits[:, offset : offset + size], dim=-1)
                offset += size
                chosen = self.discrete[index, branch : branch + 1]
                entropies.append(-log_p.gather(-1, chosen).squeeze(-1))
            loss = loss + torch.stack(entropies).mean()
        return loss
