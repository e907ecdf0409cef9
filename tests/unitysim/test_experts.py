"""The scripted experts solve their tasks (a demo of a bad expert is worthless), measured on
the environments themselves against uniform random play; the protocol path is
``tests/driver/test_record_demo.py``'s."""

from __future__ import annotations

import numpy as np
import pytest

from unitysim.envs import load
from unitysim.envs.base import Actions, AgentInfos, Output, Parameters, SimEnv
from unitysim.experts import EXPERTS, LEFT, RIGHT, Expert, expert_for, rays, toward


def decide(
    env: SimEnv, infos: AgentInfos, player: Expert | None, rng: np.random.Generator, moves: int
) -> Output:
    """One step of the agents deciding in ``infos`` (one branch): the expert's moves, or
    uniform among the first ``moves`` without one; ended episodes are forgotten first."""
    (behavior,) = env.behaviors
    deciding = ~infos.done
    ids = infos.agent_id[deciding]
    if player is not None:
        player.forget(infos.agent_id[infos.done])
        actions = player.act(ids, [o[deciding] for o in infos.obs])
    else:
        actions = rng.integers(0, moves, (len(ids), 1)).astype(np.int32)
    return env.step({behavior.name: Actions(np.zeros((len(ids), 0), np.float32), actions)})


def play(env_name: str, episodes: int, expert: bool, seed: int = 0) -> tuple[float, float]:
    """(success rate, mean return) over the first ``episodes`` episodes to end."""
    env_class = load(env_name)
    env = env_class(np.random.default_rng(seed), 1, Parameters())
    (behavior,) = env_class.behaviors
    player = expert_for(behavior.name, seed)
    assert player is not None
    rng = np.random.default_rng(seed)
    output, returns, ended = env.reset(), {}, []
    while len(ended) < episodes:
        infos = output[behavior.name]
        for row, agent in enumerate(infos.agent_id.tolist()):
            returns[agent] = returns.get(agent, 0.0) + float(infos.reward[row])
            if infos.done[row]:
                ended.append((returns.pop(agent), float(infos.reward[row]) > 0.5))
        output = decide(env, infos, player if expert else None, rng, moves=5)
    returns_, solved = zip(*ended[:episodes], strict=True)
    return float(np.mean(solved)), float(np.mean(returns_))


def test_hallway_expert_goes_to_the_goal_of_the_symbols_colour():
    success, mean_return = play("Hallway", 40, expert=True)
    assert success >= 0.85 and mean_return > 0.6  # measured over 100 (seeds 2-4): 0.87-0.90
    assert play("Hallway", 40, expert=False)[0] <= 0.4  # measured over 100: 0.23


def test_pyramids_expert_presses_the_switch_and_reaches_the_gold():
    success, mean_return = play("Pyramids", 40, expert=True)
    random_success, random_return = play("Pyramids", 20, expert=False)
    assert success >= 0.7 and mean_return >= 1.0  # measured over 100: 0.92, 1.49
    assert random_success <= 0.2 and random_return < 0.0  # measured over 60: 0.03, -0.93


def crawl(decisions: int, expert: bool, seed: int = 0) -> tuple[float, int]:
    """(reward per agent and decision, targets touched) of ten Crawlers."""
    env = load("Crawler")(np.random.default_rng(seed), 1, Parameters())
    (behavior,) = env.behaviors
    player = expert_for(behavior.name, seed)
    assert player is not None
    rng = np.random.default_rng(seed)
    output, total, touched = env.reset(), 0.0, 0
    for _ in range(decisions):
        infos = output[behavior.name]
        deciding = ~infos.done
        ids = infos.agent_id[deciding]
        if expert:
            actions = player.act(ids, [o[deciding] for o in infos.obs])
            assert actions.dtype == np.float32 and actions.shape == (len(ids), 20)
        else:
            actions = rng.uniform(-1.0, 1.0, (len(ids), 20)).astype(np.float32)
        targets = env.body.target.copy()
        output = env.step({behavior.name: Actions(actions, np.zeros((len(ids), 0), np.int32))})
        total += float(output[behavior.name].reward.sum())
        touched += int((env.body.target != targets).sum())
    return total / (10 * decisions), touched


def test_crawler_expert_walks_to_the_target_at_the_episodes_speed():
    """Each decision is 5 physics steps, each paying at most 1 for speed and facing."""
    reward, touched = crawl(300, expert=True)
    random_reward, _ = crawl(100, expert=False)
    assert reward >= 3.0 and touched >= 30  # measured: 3.82 a decision
    assert random_reward < 0.5  # measured: 0.16


def first_episodes(expert: bool, seed: int = 0, decisions: int = 1000) -> tuple[float, float]:
    """PushBlock's 32 agents: (share whose first episode scores within ``decisions``, mean
    decisions those took)."""
    env = load("PushBlock")(np.random.default_rng(seed), 1, Parameters())
    (behavior,) = env.behaviors
    player = expert_for(behavior.name, seed)
    assert player is not None
    rng = np.random.default_rng(seed)
    output, first = env.reset(), {}
    for decision in range(decisions):
        infos = output[behavior.name]
        for row, agent in enumerate(infos.agent_id.tolist()):
            if infos.done[row] and agent not in first:
                first[agent] = (float(infos.reward[row]) > 0.5, decision)
        if len(first) == 32:
            break
        output = decide(env, infos, player if expert else None, rng, moves=7)
    took = [at for scored, at in first.values() if scored]
    return len(took) / 32, float(np.mean(took))


def test_pushblock_expert_faces_the_goal_and_pushes_the_block_in():
    """First episodes, 1,000 decisions (PushBlock's MaxStep) each at most."""
    share, took = first_episodes(expert=True)
    random_share, random_took = first_episodes(expert=False)
    assert share >= 0.8 and took <= 160  # measured (seeds 0-2): 0.75-0.94, 108-127
    assert random_share <= 0.6 and random_took >= 250  # measured: 0.31-0.50, 297-491


def test_ray_reading_and_steering():
    frame = np.zeros((1, 3 * 7), np.float32)  # 3 rays, 5 tags: one-hot, missed, fraction
    frame[0, 0 * 7 + 4], frame[0, 0 * 7 + 6] = 1.0, 0.5  # ahead: a wall at half length
    frame[0, 1 * 7 + 5], frame[0, 1 * 7 + 6] = 1.0, 1.0  # right: nothing
    frame[0, 2 * 7 + 2], frame[0, 2 * 7 + 6] = 1.0, 0.2  # left: tag 2
    tags, fractions = rays(frame, 5)
    assert tags.tolist() == [[4, -1, 2]] and fractions.tolist() == [[0.5, 1.0, pytest.approx(0.2)]]
    assert toward(tags[0] == 2) == LEFT and toward(np.array([0, 1, 0], bool)) == RIGHT
    assert toward(tags[0] == 3) is None


def test_experts_forget_ended_episodes():
    expert = expert_for("Hallway?team=0")
    assert expert is not None
    assert sorted(EXPERTS) == [
        "Crawler?team=0",
        "Hallway?team=0",
        "PushBlock?team=0",
        "Pyramids?team=0",
    ]
    obs = [np.zeros((2, 105), np.float32), np.zeros((2, 3), np.float32)]
    obs[0][:, 70 + 3] = 1.0  # the newest frame's first ray sees the red block
    expert.act(np.array([7, 8]), obs)
    assert expert.goal == {7: expert.RED_GOAL, 8: expert.RED_GOAL}
    expert.forget([7])
    assert 7 not in expert.goal and 7 not in expert.unseen and 8 in expert.goal
    assert expert_for("3DBall?team=0") is None
