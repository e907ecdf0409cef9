"""PushBlock's and PushBlockCollab's stand-ins: the examples' specs through the real client
(the collab's six-channel grid decoded from two PNGs), and the court's rules."""

from __future__ import annotations

import numpy as np
from mlagents_envs.base_env import ActionTuple

from tests.unitysim.test_learnable_envs import make, random_actions
from unitysim.envs.base import Actions
from unitysim.envs.push_block import (
    AGENT_TAG,
    GOAL_TAG,
    GRID,
    WALL_TAG,
    PushBlock,
    PushBlockCollab,
)

FORWARD = 1
SOLO, COLLAB = "PushBlock?team=0", "PushBlockCollab?team=0"


def test_the_real_client_sees_pushblocks_stacked_rays_and_the_collabs_png_grid(open_env):
    with open_env("PushBlock", no_graphics=True) as env:
        env.reset()
        spec = env.behavior_specs[SOLO]
        assert [(o.name, o.shape) for o in spec.observation_specs] == [
            ("StackingSensor_size3_OffsetRayPerceptionSensor", (105,)),
            ("StackingSensor_size3_RayPerceptionSensor", (105,)),
        ]
        assert spec.action_spec.discrete_branches == (7,)
        decisions, _ = env.get_steps(SOLO)
        assert len(decisions) == 32 and not np.asarray(decisions.group_id).any()
        # the first frame of a stack is the current one after the reset's zeros
        assert (decisions.obs[1][:, :70] == 0).all() and (decisions.obs[1][:, 70:] != 0).any()
    with open_env("PushBlockCollab", no_graphics=True) as env:
        env.reset()
        spec = env.behavior_specs[COLLAB]
        assert [(o.name, o.shape) for o in spec.observation_specs] == [("GridSensor", (6, 20, 20))]
        decisions, _ = env.get_steps(COLLAB)
        groups = np.asarray(decisions.group_id).tolist()
        assert sorted(groups) == [g for g in (1, 2, 3, 4) for _ in range(3)]
        grid = decisions.obs[0]
        assert set(np.unique(grid).tolist()) == {0.0, 1.0}  # decoded exactly from the PNGs
        assert (grid.sum(1) <= 1).all()  # one tag per cell
        assert grid[:, 3:].any(axis=(0, 2, 3)).all()  # blocks of every size in sight
        env.set_actions(COLLAB, ActionTuple(discrete=np.ones((12, 1), dtype=np.int32)))
        env.step()


def push_to_goal(env: PushBlock) -> np.ndarray:
    """A scripted player: get behind the block (the side away from the goal), then walk
    through it towards the goal."""
    block = env.blocks[env.field, 0]
    lined = (np.abs(env.pos[:, 0] - block[:, 0]) < 0.6) & (env.pos[:, 1] > block[:, 1])
    target = np.where(lined[:, None], block - np.array([0.0, 3.0]), block + np.array([0.0, 2.0]))
    way = target - env.pos
    error = (np.arctan2(way[:, 1], way[:, 0]) - env.heading + np.pi) % (2 * np.pi) - np.pi
    return np.where(error > 0.35, 4, np.where(error < -0.35, 3, FORWARD))


def episodes(policy: str, decisions: int = 1500) -> list[float]:
    env = make("PushBlock", seed=0)
    assert isinstance(env, PushBlock)
    rng = np.random.default_rng(1)
    out, returns, gathered = env.reset(), [], np.zeros(env.n)
    for _ in range(decisions):
        infos = out[SOLO]
        for agent, reward, done in zip(infos.agent_id, infos.reward, infos.done, strict=True):
            gathered[agent] += reward  # a terminal row comes before its agent's next one
            if done:
                returns.append(gathered[agent])
                gathered[agent] = 0.0
        if policy == "random":
            actions = random_actions(env, out, rng)
        else:
            rows = infos.agent_id[~infos.done]
            moves = push_to_goal(env)[rows, None].astype(np.int32)
            actions = {SOLO: Actions(np.zeros((len(rows), 0), np.float32), moves)}
        out = env.step(actions)
    return returns


def test_a_block_pushed_into_the_goal_pays_five_and_random_moves_rarely_do():
    scripted, random = episodes("scripted"), episodes("random")
    # an episode ends at a goal (+5 less the time) or at MaxStep (-1)
    assert all(r > 4.0 or r == np.float32(-1.0) or abs(r + 1.0) < 1e-3 for r in scripted)
    assert len(scripted) > 4 * len(random)  # many more goals in the same time
    assert np.mean(scripted) > np.mean(random) + 1.0


def collab_at(positions: list[tuple[float, float]], heading: float) -> PushBlockCollab:
    """Field 0 with its agents placed and facing ``heading``, every block far away."""
    env = make("PushBlockCollab", seed=0)
    assert isinstance(env, PushBlockCollab)
    env.reset()
    env.blocks[0] = [[-11.0 + 3.5 * b, 11.0] for b in range(6)]  # a row along the far wall
    env.pos[:3] = positions
    env.heading[:3] = heading
    env.velocity[:3] = 0.0
    return env


def walk(env: PushBlockCollab, agents: int, steps: int) -> np.ndarray:
    """The first ``agents`` walk forward for ``steps`` physics steps; which agents' episodes
    ended on the last one."""
    moves = np.zeros((env.n, 1), dtype=np.int32)
    moves[:agents] = FORWARD
    env._act(np.arange(env.n), Actions(np.zeros((env.n, 0), np.float32), moves))
    for _ in range(steps):
        ended = env._simulate()[0]
    return ended


def test_a_large_block_moves_for_two_agents_pushing_together_not_for_one():
    for agents, moved in ((1, False), (2, True)):
        env = collab_at([(-0.5, 3.0), (0.5, 3.0), (-8.0, 8.0)], heading=-np.pi / 2)
        env.blocks[0, 2] = (0.0, 0.0)  # a 2 x 2 block (worth 2) just ahead of the pair
        walk(env, agents, steps=15)
        assert (env.blocks[0, 2, 1] < -1.0) == moved, env.blocks[0, 2]
        assert (env.pos[:agents, 1] > env.blocks[0, 2, 1] + 1.4).all()  # never through it


def test_a_block_in_the_goal_vanishes_and_pays_its_worth_to_the_group_then_the_last_ends_it():
    env = collab_at([(0.0, -5.0), (5.0, 5.0), (-5.0, 5.0)], heading=-np.pi / 2)
    env.blocks[0, 0] = (0.0, -6.5)  # a small block between the agent and the goal
    env.blocks[0, 1:] = 1.0e4  # the others already in
    env.active[0, 1:] = False
    env.group_reward[:] = 0.0
    for _ in range(50):
        ended = walk(env, 1, steps=1)
        if ended[0]:
            break
    assert ended[:3].all() and not ended[3:].any()  # the group's episode, not the others'
    assert np.allclose(env.group_reward[:3], 1.0, atol=0.05)
    assert not env.active[0, 0]


def test_the_grid_turns_with_the_agent_and_shows_the_goal_the_walls_and_the_others():
    # facing -y, so +x is to the agent's left; the second agent 5 behind, the third 3 left
    env = collab_at([(5.0, -3.0), (5.0, 2.0), (8.0, -3.0)], heading=-np.pi / 2)
    (grid,) = env._observe(0, np.arange(3))
    cells = (GRID / 2 - 0.5 - np.arange(GRID)).tolist()  # ahead by row, left by column
    row, col = cells.index, cells.index
    mine = grid[0]
    assert (mine.sum(0) <= 1).all()
    # the goal from y = -7.85 (5.5 ahead and on), over the wall where both are
    assert mine[GOAL_TAG, row(5.5)].all() and not mine[GOAL_TAG, row(4.5)].any()
    assert mine[GOAL_TAG, row(9.5)].all()
    # the wall at x = 12.5: the column 7.5 to the left, not the one 6.5 to the left
    assert mine[WALL_TAG, row(4.5) :, col(7.5)].all()
    assert not mine[WALL_TAG, :, col(6.5)].any()
    others = {(cells[r], cells[c]) for r, c in zip(*np.nonzero(mine[AGENT_TAG]), strict=True)}
    assert others == {(a, s) for a in (-4.5, -5.5) for s in (-0.5, 0.5)} | {
        (a, s) for a in (-0.5, 0.5) for s in (2.5, 3.5)
    }
    assert not mine[3:].any()  # every block far away along the +y wall, out of sight
