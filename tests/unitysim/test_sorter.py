"""Sorter's stand-in: the example's spec (a BufferSensor among its sensors) through the real
client, and its rules at the environment level."""

from __future__ import annotations

import numpy as np
from mlagents_envs.base_env import ActionTuple, DimensionProperty

from tests.unitysim.test_learnable_envs import check_infos, make, random_actions
from unitysim.envs.base import Actions
from unitysim.envs.sorter import ROW, TILES, Sorter

BEHAVIOR = "Sorter?team=0"


def still(n: int) -> dict[str, Actions]:
    return {BEHAVIOR: Actions(np.zeros((n, 0), np.float32), np.zeros((n, 3), np.int32))}


def to_next_decision(env: Sorter) -> tuple[dict[int, float], list[int], np.ndarray]:
    """Step without moving until the next decisions: each agent's reward over the messages,
    the agents whose episode ended, the decisions' buffers by agent id order."""
    rewards: dict[int, float] = {}
    ended: list[int] = []
    actions = still(8)
    while True:
        out = env.step(actions)[BEHAVIOR]
        actions = {}
        for agent, reward in zip(out.agent_id.tolist(), out.reward.tolist(), strict=True):
            rewards[agent] = rewards.get(agent, 0.0) + reward
        ended += out.agent_id[out.done].tolist()
        if (~out.done).any():
            return rewards, ended, out.obs[0][~out.done][np.argsort(out.agent_id[~out.done])]


def test_the_real_client_sees_the_examples_spec(open_env):
    with open_env("Sorter", no_graphics=True) as env:
        env.reset()
        assert list(env.behavior_specs) == [BEHAVIOR]
        spec = env.behavior_specs[BEHAVIOR]
        names = [o.name for o in spec.observation_specs]
        assert names == ["BufferSensor", "RBSensor", "StackingSensor_size2_VectorSensor_size4"]
        assert [o.shape for o in spec.observation_specs] == [(20, 23), (10,), (8,)]
        assert spec.observation_specs[0].dimension_property == (
            DimensionProperty.VARIABLE_SIZE,
            DimensionProperty.NONE,
        )
        assert spec.action_spec.discrete_branches == (3, 3, 3)
        assert spec.action_spec.continuous_size == 0
        decisions, _ = env.get_steps(BEHAVIOR)
        assert len(decisions) == 8  # eight areas, one agent each
        buffer = decisions.obs[0]
        present = (buffer**2).sum(-1) >= 0.01
        assert present.any(1).all()  # at least one tile each
        # the rows Unity filled come first, the padding after
        assert all((~row[int(row.sum()) :]).all() for row in present)
        env.set_actions(BEHAVIOR, ActionTuple(discrete=np.ones((8, 3), np.int32)))
        env.step()


def test_tiles_are_listed_in_increasing_number_with_their_place_and_state():
    env = make("Sorter", seed=2, num_tiles=6)
    out = env.reset()
    check_infos(env, out)
    buffer = out[BEHAVIOR].obs[0]
    for agent in range(8):
        spawned = np.flatnonzero(env.slot[agent] >= 0)
        rows = buffer[agent]
        assert 1 <= len(spawned) <= 6
        assert not rows[len(spawned) :].any()  # padding: zeros
        numbers = rows[: len(spawned), 1:TILES].argmax(1) + 1  # tile 20's one-hot is overwritten
        np.testing.assert_array_equal(
            numbers[spawned < TILES - 1], spawned[spawned < TILES - 1] + 1
        )
        # the agent is at the centre: each tile's offset is its place on the circle, over 20
        offset = rows[: len(spawned), TILES : TILES + 2]
        np.testing.assert_allclose(np.hypot(*offset.T), 20.5 / 20, rtol=1e-5)
        assert (rows[: len(spawned), ROW - 1] == 0).all()  # none visited yet
    assert buffer.shape == (8, TILES, ROW)


def test_the_lowest_tile_pays_one_another_ends_the_episode():
    env = make("Sorter", seed=0, num_tiles=4)
    env.reset()
    assert isinstance(env, Sorter)
    env.slot[:] = -1
    env.slot[:, [2, 5, 9]] = [[0, 5, 10]] * 8  # tiles 3, 6, 10 in slots 0, 5, 10
    places = env._tile_positions()
    env.pos[0] = places[0, 2] * 19.4 / 20.5  # at tile 3, the lowest: +1
    env.pos[1] = places[1, 5] * 19.4 / 20.5  # at tile 6 first: -1 and the end
    rewards, ended, buffers = to_next_decision(env)
    assert rewards[0] > 0.99 and env.visited[0, 2]
    assert ended == [1] and rewards[1] < -0.99
    # the visited tile shows as visited, and touching it again does nothing
    assert buffers[0][0, ROW - 1] == 1.0 and buffers[0][1, ROW - 1] == 0.0
    rewards, ended, _ = to_next_decision(env)
    assert abs(rewards[0]) < 0.01 and ended == []
    # the other two in order: the episode ends, solved
    for tile in (5, 9):
        env.pos[0] = env._tile_positions()[0, tile] * 19.4 / 20.5
        rewards, ended, _ = to_next_decision(env)
        assert rewards[0] > 0.99
    assert 0 in ended


def test_a_random_policy_rarely_sorts():
    """Over 1000 messages of 8 agents with 2 tiles at most: most episodes run out of time
    (-1) or end at a wrong tile; a sorted one returns about +1 or +2."""
    env = make("Sorter", seed=1, num_tiles=2)
    rng = np.random.default_rng(0)
    out = env.reset()
    total, episodes = 0.0, 0
    for _ in range(1000):
        out = env.step(random_actions(env, out, rng))
        total += float(out[BEHAVIOR].reward.sum())
        episodes += int(out[BEHAVIOR].done.sum())
    assert episodes >= 4
    assert total / episodes < 0.5  # a solved episode returns 1 or 2
