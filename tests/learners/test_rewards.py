"""Every trainer trains on the group reward, as mlagents-learn 1.1.0's extrinsic signal
adds it to each agent's own (its ``ExtrinsicRewardProvider``): what each algorithm keeps
of a step whose reward is 0.5 and whose group reward is 1, at strength 2."""

from __future__ import annotations

import dataclasses

import torch

from batches import keys
from learners.acting.factory import network_settings
from learners.algorithms.impala import IMPALA
from learners.algorithms.ppo import PPO
from learners.algorithms.sac import SAC
from learners.networks.policies import ActorCritic
from learners.trainer_config.parse import defaults
from testkit.segments import segment, vector_spec

SPEC = vector_spec(4, continuous=1)


def settings(trainer: str):
    return dataclasses.replace(defaults(trainer), reward_strength=2.0)


def rewarded(steps: int = 8):
    batch = segment(SPEC, 1, steps)
    batch[keys.NEXT, keys.REWARD] = torch.full((steps, 1), 0.5)
    batch[keys.NEXT, keys.GROUP_REWARD] = torch.ones(steps, 1)
    return batch


def test_ppo_keeps_the_agents_and_its_groups_reward():
    ppo = PPO(ActorCritic(SPEC), settings("ppo"))
    ppo.add(rewarded(), torch.zeros(8, dtype=torch.int64))
    torch.testing.assert_close(ppo.store.take().reward, torch.full((8,), 1.5))


def test_impala_scales_the_agents_and_its_groups_reward():
    impala = IMPALA(ActorCritic(SPEC), settings("impala"))
    impala.add(rewarded(), torch.zeros(8, dtype=torch.int64))
    batch = impala.buffer.take(impala.network, impala.settings.reward_strength)
    torch.testing.assert_close(batch[keys.NEXT, keys.REWARD], torch.full((8, 1), 3.0))


def test_sac_replays_the_agents_and_its_groups_reward():
    config = settings("sac")
    sac = SAC(ActorCritic(SPEC, network_settings(config)), config)
    sac.add(rewarded(), torch.zeros(8, dtype=torch.int64))
    stored = sac.buffer.sample()[keys.NEXT, keys.REWARD]
    torch.testing.assert_close(stored, torch.full_like(stored, 3.0))
