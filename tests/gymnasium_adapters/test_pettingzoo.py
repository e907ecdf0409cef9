"""The PettingZoo adapter over real unitysim players (real gRPC, no mocks): PettingZoo's own
``parallel_api_test`` on builds whose agents come and go (DungeonEscape's sacrifice and
new ids), with two behaviors (SoccerTwos), and agents that change behavior (WallJump);
every agent of every behavior exposed; names per episode; group ids and rewards."""

from __future__ import annotations

import warnings
from collections import Counter

import pytest
from pettingzoo.test import parallel_api_test

from gymnasium_adapters.pettingzoo_env import UnityParallelEnv, behavior_of
from tests.helpers import leak_checked_allocator

pytestmark = pytest.mark.integration


@pytest.fixture
def allocator(tmp_path):
    with leak_checked_allocator(tmp_path, 24700, 24799) as allocator:
        yield allocator


@pytest.mark.parametrize("build", ["DungeonEscape", "SoccerTwos", "WallJump"])
def test_pettingzoos_parallel_api_test_passes(build, allocator):
    env = UnityParallelEnv(f"unitysim:{build}", allocator=allocator, seed=1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # its notes on agents that come and go
            parallel_api_test(env, num_cycles=300)
    finally:
        env.close()


def test_every_agent_of_every_behavior_and_new_names_per_episode(allocator):
    env = UnityParallelEnv("unitysim:SoccerTwos", allocator=allocator, seed=3)
    try:
        obs, infos = env.reset()
        behaviors = {behavior_of(a) for a in env.agents}
        assert (
            behaviors
            == set(env.unity.behavior_specs)
            == {
                "SoccerTwos?team=0",
                "SoccerTwos?team=1",
            }
        )
        assert set(obs) == set(env.agents)
        per_team = Counter(behavior_of(a) for a in env.agents)
        assert per_team["SoccerTwos?team=0"] == per_team["SoccerTwos?team=1"] >= 2
        players = len(env.agents)
        assert all(infos[a]["group_id"] > 0 for a in env.agents)  # each team is a group
        ended, group_rewards, seen = set(), [], set(env.agents)
        for _ in range(2000):
            actions = {a: env.action_space(a).sample() for a in env.agents}
            obs, rewards, terminated, truncated, infos = env.step(actions)
            done = {a for a in rewards if terminated[a] or truncated[a]}
            assert not done & set(env.agents)  # an ended agent leaves ...
            ended |= done
            assert not ended & set(env.agents)  # ... for good: its next episode is a new name
            group_rewards += [infos[a]["group_reward"] for a in done]
            seen |= set(env.agents)
            if len(ended) >= players and any(group_rewards):
                break
        assert len(ended) >= players, "as many episodes ended as there are players"
        assert any(r != 0 for r in group_rewards), "a goal paid its group reward"
        assert any("&episode=1" in a for a in seen)  # the same Unity agent, next episode
        assert set(env.possible_agents) >= seen
    finally:
        env.close()


def test_a_closed_env_is_one_line(allocator):
    env = UnityParallelEnv("unitysim:Basic", allocator=allocator)
    env.close()
    with pytest.raises(Exception, match="closed"):
        env.step({})
