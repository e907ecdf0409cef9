"""SAC with reward signals besides the extrinsic one, as ML-Agents' SAC: a reward stream
per signal in the Q networks, each with its reward, gamma and episode ends; the signals'
networks trained on batches of their own; their ML-Agents tags; checkpoints."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from batches import keys
from learners.algorithms.sac import SAC
from learners.networks.policies import ActorCritic
from learners.trainer_config.parse import defaults
from learners.trainer_config.settings import NetworkSettings, RewardSignalSettings
from testkit.segments import segment, vector_spec

SMALL = NetworkSettings(hidden_units=16, num_layers=1)


def build(spec, gamma: float = 0.9, strength: float = 2.0) -> SAC:
    base = defaults("sac")
    rnd = RewardSignalSettings("rnd", gamma=gamma, strength=strength, network_settings=SMALL)
    network = replace(SMALL, tanh_squash=True, conditional_sigma=True)
    h = replace(base.hyperparameters, batch_size=32, buffer_init_steps=0, steps_per_update=4.0)
    settings = replace(base, hyperparameters=h, network_settings=network, reward_signals=(rnd,))
    torch.manual_seed(0)
    return SAC(ActorCritic(spec, network), settings)


def ended(spec):
    """A segment of 4 pieces of 16 steps, each piece's last step ending its episode."""
    batch = segment(spec, 4, 16)
    done = batch[keys.NEXT, keys.DONE]
    batch[keys.NEXT, keys.TERMINATED] = done.clone()
    batch[keys.NEXT, keys.TRUNCATED] = torch.zeros_like(done)
    return batch


def test_each_stream_has_its_reward_gamma_and_episode_ends():
    """The extrinsic stream stops at an episode's end; RND's goes on (ML-Agents'
    ``ignore_done``) with its own gamma, its reward the signal's times its strength."""
    spec = vector_spec(4, 2, ())
    sac = build(spec)
    assert sac.streams == 2 and sac.q[0].body[-1].out_features == 2
    data = ended(spec)
    sac.add(data, torch.zeros(len(data), dtype=torch.int64))
    batch = sac.buffer.storage[: len(sac.buffer)]
    alpha = sac.log_alpha.detach().exp()
    torch.manual_seed(1)
    target = sac.target(batch, alpha)  # [steps, 2]
    torch.manual_seed(1)
    reward = sac.signals.rewards(batch)[:, 0]
    ends = batch[keys.NEXT, keys.TERMINATED][:, 0]
    assert ends.sum() == 4
    torch.testing.assert_close(target[ends, 0], batch[keys.NEXT, keys.REWARD][ends, 0])
    assert (target[ends, 1] - reward[ends]).abs().min() > 0  # bootstrapped past the end
    rnd = sac.signals.items[0]
    steps = sac.signals.transitions(batch)
    torch.testing.assert_close(reward, rnd.rewards(steps) * 2.0)
    # a stronger signal, or another gamma, moves only its own stream
    other = build(spec, gamma=0.5, strength=4.0)
    other.q.load_state_dict(sac.q.state_dict())
    other.q_target.load_state_dict(sac.q_target.state_dict())
    other.signals.items[0].load_state_dict(rnd.state_dict())
    other.network.load_state_dict(sac.network.state_dict())
    torch.manual_seed(1)
    moved = other.target(batch, alpha)
    torch.testing.assert_close(moved[:, 0], target[:, 0])
    assert not torch.allclose(moved[:, 1], target[:, 1])


def test_the_signals_train_report_and_round_trip():
    spec = vector_spec(4, 0, (3,))
    sac = build(spec)
    for seed in range(3):
        data = segment(spec, 4, 16, seed=seed)
        sac.add(data, torch.zeros(len(data), dtype=torch.int64))
    assert sac.ready()
    first = sac.update(0.0)
    for tag in ("Losses/RND Loss", "Policy/Rnd Reward", "Losses/Q1 Loss"):
        assert tag in first, first
    for _ in range(20):
        data = segment(spec, 4, 16, seed=0)  # the same states again: RND's error falls
        sac.add(data, torch.zeros(len(data), dtype=torch.int64))
        last = sac.update(0.0)
    assert last["Losses/RND Loss"] < first["Losses/RND Loss"]
    fresh = build(spec)
    fresh.load_state_dict(sac.state_dict())
    batch = sac.buffer.sample()
    steps = sac.signals.transitions(batch)
    torch.testing.assert_close(
        fresh.signals.items[0].rewards(steps), sac.signals.items[0].rewards(steps)
    )


def test_signal_rewards_are_reported_per_episode_as_they_arrive():
    """As ML-Agents' SAC: each signal rewards the steps as they arrive and
    ``Policy/<Signal> Reward`` is the mean per-episode sum, over episodes spanning several
    segments; an update after which no episode ended reports none."""
    spec = vector_spec(4, 2, ())
    sac = build(spec)  # strength 2
    agents = torch.arange(4).repeat_interleave(16)
    first = segment(spec, 4, 16, seed=0)  # every row cut at a horizon: episodes go on
    first[keys.AGENT_ID] = agents
    first[keys.NEXT, keys.CUT] = first[keys.NEXT, keys.DONE].clone()
    sac.add(first, torch.zeros(64, dtype=torch.int64))
    rewards_first = sac.signals.rewards(sac.buffer.storage[:64])[:, 0]
    assert sac.ready() and "Policy/Rnd Reward" not in sac.update(0.0)
    second = ended(spec)  # the same agents' episodes end at their rows' last steps
    second[keys.AGENT_ID] = agents
    sac.add(second, torch.zeros(64, dtype=torch.int64))
    rewards_second = sac.signals.rewards(sac.buffer.storage[64:128])[:, 0]
    per_episode = rewards_first.reshape(4, 16).sum(1) + rewards_second.reshape(4, 16).sum(1)
    report = sac.update(0.0)
    assert report["Policy/Rnd Reward"] == pytest.approx(float(per_episode.mean()), rel=1e-5)
