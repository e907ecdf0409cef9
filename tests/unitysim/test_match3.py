"""Match3's stand-in: the example's four behaviors through the real client (the visual one's
six and three channels decoded from concatenated PNGs), and the board's rules."""

from __future__ import annotations

import numpy as np
from mlagents_envs.base_env import ActionTuple

from tests.unitysim.test_learnable_envs import check_infos, make, random_actions
from unitysim.envs.base import Actions
from unitysim.envs.match3 import (
    COLUMNS,
    MOVE_COLUMN,
    MOVE_ROW,
    MOVES,
    OTHER_COLUMN,
    OTHER_ROW,
    ROWS,
    Match3,
    matched,
)

NAMES = ["Match3SimpleHeuristic", "Match3SmartHeuristic", "Match3VectorObs", "Match3VisualObs"]
BEHAVIORS = [f"{name}?team=0" for name in NAMES]
CELLS, SPECIAL = "Match3 Sensor (cells)", "Match3 Sensor (special)"


def test_the_real_client_sees_the_examples_four_behaviors(open_env):
    with open_env("Match3", no_graphics=True) as env:
        env.reset()
        assert sorted(env.behavior_specs) == BEHAVIORS
        for name in BEHAVIORS:
            spec = env.behavior_specs[name]
            assert [o.name for o in spec.observation_specs] == [CELLS, SPECIAL]
            visual = name.startswith("Match3VisualObs")
            shapes = [(6, 9, 8), (3, 9, 8)] if visual else [(432,), (216,)]
            assert [o.shape for o in spec.observation_specs] == shapes
            assert spec.action_spec.discrete_branches == (127,)
            assert spec.action_spec.continuous_size == 0
        counts = {}
        for name in BEHAVIORS:
            visual = name.startswith("Match3VisualObs")
            decisions, _ = env.get_steps(name)
            counts[name.split("?")[0]] = len(decisions)
            for sensor, values in zip(decisions.obs, (6, 3), strict=True):
                # one-hot where the board is, zeros outside it, after the PNGs' decoding too
                assert set(np.unique(sensor).tolist()) <= {0.0, 1.0}
                per_cell = sensor.sum(1) if visual else sensor.reshape(-1, 9, 8, values).sum(-1)
                assert ((per_cell == 1) | (per_cell == 0)).all()
                assert (per_cell[:, :6, :6] == 1).all()  # every board has at least 6 x 6
            assert (decisions.action_mask[0].sum(1) < 127).all()  # a valid move on each board
            env.set_actions(name, ActionTuple(discrete=decisions.action_mask[0].argmin(1)[:, None]))
        assert counts == dict(zip(NAMES, [2, 2, 4, 4], strict=True))
        env.step()


def test_the_mask_allows_exactly_the_swaps_that_make_a_line_on_the_board():
    env = make("Match3", seed=3, num_areas=2)
    assert isinstance(env, Match3)
    for _ in range(5):
        env._begin(env.ids)
        assert not matched(env.cells).any()  # dealt settled
        fast = env._valid(env.ids)
        for board in range(env.n):
            for move in range(MOVES):
                r, c, r2, c2 = (
                    MOVE_ROW[move],
                    MOVE_COLUMN[move],
                    OTHER_ROW[move],
                    OTHER_COLUMN[move],
                )
                inside = r2 < env.height[board] and c2 < env.width[board]
                cells = env.cells[board : board + 1].copy()
                cells[0, r, c], cells[0, r2, c2] = cells[0, r2, c2], cells[0, r, c]
                assert fast[board, move] == (inside and bool(matched(cells).any())), (board, move)
        assert ((env.height >= 6) & (env.height <= ROWS)).all()
        assert ((env.width >= 6) & (env.width <= COLUMNS)).all()


def test_a_move_clears_its_line_pays_its_points_and_the_pieces_above_drop():
    env = make("Match3", seed=5)
    assert isinstance(env, Match3)
    out = env.reset()
    board = 4  # Match3VectorObs's first board
    env.height[board], env.width[board] = 9, 8
    # columns 0..7 of row 0: 0 0 1 0 2 3 4 5; above: a pattern with no line of three
    pattern = (np.arange(ROWS)[:, None] + 2 * np.arange(COLUMNS)[None, :]) % 6
    cells = np.where(pattern == 0, 3, pattern)
    cells[0] = [0, 0, 1, 0, 2, 3, 4, 5]
    env.cells[board], env.special[board] = cells, 0
    env.special[board, 0, 3] = 2  # the piece that moves in is worth 3 points
    assert not matched(env.cells[board : board + 1]).any()
    above = env.cells[board, 1:, :4].copy()
    env.valid_moves = env._valid(env.ids)
    swap = 2  # row 0: the cells of columns 2 and 3 change places: 0 0 0 1 ...
    assert env.valid_moves[board, swap]
    actions = random_actions(env, out, np.random.default_rng(0))
    actions["Match3VectorObs?team=0"].discrete[0, 0] = swap
    after = env.step(actions)["Match3VectorObs?team=0"]
    reward = after.reward[after.agent_id == board][0]
    # 0.01 a point: two basic pieces and a type-2 special (with this seed nothing falls into
    # a line after): columns 0..2 dropped by one towards row 0, new pieces on top
    assert np.isclose(reward, 0.01 * (1 + 1 + 3))
    np.testing.assert_array_equal(env.cells[board, :-1, :3], above[:, :3])
    assert not matched(env.cells[board : board + 1]).any()
    check_infos(env, {"Match3VectorObs?team=0": after})


def test_a_masked_move_changes_nothing_and_heuristics_ignore_python():
    env = make("Match3", seed=7)
    assert isinstance(env, Match3)
    out = env.reset()
    before = env.cells.copy()
    actions = random_actions(env, out, np.random.default_rng(1))
    learners = env.rows_of[2]
    invalid = np.argmin(env.valid_moves[learners], axis=1)  # a masked move on each board
    actions["Match3VectorObs?team=0"].discrete[:, 0] = invalid
    for name in ("Match3SimpleHeuristic?team=0", "Match3SmartHeuristic?team=0"):
        actions[name] = Actions(actions[name].continuous, np.full((2, 1), MOVES - 1, np.int32))
    env.step(actions)
    np.testing.assert_array_equal(env.cells[learners], before[learners])
    heuristic = np.concatenate(env.rows_of[:2])
    assert (env.cells[heuristic] != before[heuristic]).any(axis=(1, 2)).all()  # they moved


def test_episodes_end_at_500_moves_and_the_greedy_heuristic_beats_random_moves():
    """The example's benchmark: a random valid move 34.2 an episode, the greedy one 37.0."""
    env = make("Match3", seed=11, num_areas=6)
    rng = np.random.default_rng(2)
    out = env.reset()
    returns = {name: 0.0 for name in BEHAVIORS}
    for step in range(1, 501):
        out = env.step(random_actions(env, out, rng))
        for name, infos in out.items():
            returns[name] += float(infos.reward.sum())
            assert infos.done.any() == (step == 500)
            assert (infos.max_step_reached == infos.done).all()
    boards = {name: len(rows) for name, rows in zip(BEHAVIORS, env.rows_of, strict=True)}
    per_board = {name: returns[name] / boards[name] for name in BEHAVIORS}
    simple, smart = per_board[BEHAVIORS[0]], per_board[BEHAVIORS[1]]
    assert 25 < simple < smart < 45, per_board
    assert abs(per_board[BEHAVIORS[2]] - simple) < 0.1 * simple  # random valid moves, too
    assert (env.moves_made == 0).all()
