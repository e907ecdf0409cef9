"""GridWorld at the environment level (plain numpy, no gRPC): its rules, seen in its images.

Why a module of its own: GridWorld's tests read the agents' camera images back into cells
(``decode``) and play a shortest-path ``oracle`` against random play, machinery the other
environments do not need. The shared helpers come from ``test_learnable_envs.py``.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from tests.unitysim.test_learnable_envs import decisions, make, random_actions
from unitysim.envs.base import GOAL_SIGNAL, Actions, AgentInfos, SimEnv

GRID = "GridWorld?team=0"
FLOOR, WALL, GREEN, RED, AGENT = range(5)
MOVES = {1: (-1, 0), 2: (1, 0), 3: (0, -1), 4: (0, 1)}


def decode(image: np.ndarray, size: int) -> np.ndarray:
    """The cells (walls included) of one (3, H, W) image, read at the cell centres."""
    span, pixels = size + 2, image.shape[-1]
    centre = ((np.arange(span) + 0.5) * pixels / span).astype(int)
    red, green, blue = (image[c][np.ix_(centre, centre)] for c in range(3))
    cells = np.full((span, span), FLOOR)
    cells[(red > 0.3) & (red < 0.7)] = WALL
    cells[(green > 0.9) & (red < 0.1)] = GREEN
    cells[(red > 0.9) & (green < 0.1)] = RED
    cells[(blue > 0.9) & (red < 0.1)] = AGENT
    return cells


def oracle(cells: np.ndarray, signal: np.ndarray) -> int:
    """First move of a shortest path to a goal of the signalled colour, around wrong goals."""
    good, bad = (GREEN, RED) if signal[0] == 1 else (RED, GREEN)
    start = tuple(np.argwhere(cells == AGENT)[0])
    first = {start: 0}
    queue = deque([start])
    while queue:
        here = queue.popleft()
        for action, (dr, dc) in MOVES.items():
            there = (here[0] + dr, here[1] + dc)
            if there in first or cells[there] in (WALL, bad):
                continue
            first[there] = first[here] or action
            if cells[there] == good:
                return first[there]
            queue.append(there)
    return 0


def episode_returns(env: SimEnv, steps: int, policy: str, seed: int = 0) -> list[float]:
    rng = np.random.default_rng(seed)
    out = env.reset()
    running: dict[int, float] = {}
    returns: list[float] = []
    for _ in range(steps):
        infos = out[GRID]
        for agent, reward, done in zip(infos.agent_id, infos.reward, infos.done, strict=True):
            running[agent] = running.get(agent, 0.0) + float(reward)
            if done:
                returns.append(running.pop(agent))
        rows = np.flatnonzero(decisions(infos))
        if policy == "oracle":
            size = int(env.params.get("gridSize", 5))
            chosen = [oracle(decode(infos.obs[0][i], size), infos.obs[1][i]) for i in rows]
            actions = Actions(np.zeros((len(rows), 0), np.float32), np.array(chosen)[:, None])
        else:
            actions = random_actions(env, out, rng)[GRID]
        out = env.step({GRID: actions})
    return returns


def test_gridworld_spec() -> None:
    behavior = make("GridWorld").behavior(GRID)
    camera, signal = behavior.sensors
    assert camera.name == "CameraSensor" and camera.png and camera.shape[0] == 3
    assert signal.name == "GoalSignal" and signal.observation_type == GOAL_SIGNAL
    assert behavior.branches == (5,) and behavior.continuous == 0


def test_gridworld_image_and_signal_show_the_layout() -> None:
    infos = make("GridWorld", seed=5).reset()[GRID]
    for image, signal in zip(infos.obs[0], infos.obs[1], strict=True):
        cells = decode(image, 5)
        assert (cells[0] == WALL).all() and (cells[-1] == WALL).all()
        assert (cells[:, 0] == WALL).all() and (cells[:, -1] == WALL).all()
        inside = cells[1:-1, 1:-1]
        assert [(inside == code).sum() for code in (WALL, GREEN, RED, AGENT)] == [0, 1, 1, 1]
        assert sorted(signal.tolist()) == [0.0, 1.0]
    targets = infos.obs[1].argmax(axis=1)
    assert 0 < targets.sum() < len(targets)  # both colours are correct somewhere


def check_masks(infos: AgentInfos, size: int) -> set[tuple[int, int]]:
    """Masks forbid exactly the moves into walls; returns the agents' positions."""
    positions = set()
    for i in np.flatnonzero(decisions(infos)):
        r, c = np.argwhere(decode(infos.obs[0][i], size) == AGENT)[0] - 1
        expected = [False, r == 0, r == size - 1, c == 0, c == size - 1]
        np.testing.assert_array_equal(infos.action_mask[i], expected)
        positions.add((int(r), int(c)))
    return positions


def test_gridworld_masks_walls_and_stays_put() -> None:
    env = make("GridWorld", seed=2)
    out = env.reset()
    rng = np.random.default_rng(0)
    for _ in range(60):
        check_masks(out[GRID], 5)
        out = env.step(random_actions(env, out, rng))
    # a masked move sent anyway leaves the agent where it was
    infos = out[GRID]
    rows = np.flatnonzero(decisions(infos))
    before = [np.argwhere(decode(infos.obs[0][i], 5) == AGENT)[0] for i in rows]
    forbidden = np.where(infos.action_mask[rows].any(axis=1), infos.action_mask[rows].argmax(1), 0)
    actions = Actions(np.zeros((len(rows), 0), np.float32), forbidden[:, None].astype(np.int32))
    after = env.step({GRID: actions})[GRID]
    assert not after.done.any()
    for i, position in zip(np.flatnonzero(decisions(after)), before, strict=True):
        np.testing.assert_array_equal(np.argwhere(decode(after.obs[0][i], 5) == AGENT)[0], position)


def test_gridworld_oracle_beats_random() -> None:
    good = episode_returns(make("GridWorld", seed=0), 250, "oracle")
    bad = episode_returns(make("GridWorld", seed=0), 250, "random")
    assert len(good) > 100 and len(bad) > 20
    assert np.mean(good) >= 0.8
    assert np.mean(bad) < 0.2


def test_gridworld_max_step_interrupts() -> None:
    env = make("GridWorld", gridSize=6, numGreenGoals=0, numRedGoals=0)
    env.reset()
    still = {GRID: Actions(np.zeros((9, 0), np.float32), np.zeros((9, 1), np.int32))}
    for _ in range(99):
        infos = env.step(still)[GRID]
        assert not infos.done.any() and (infos.reward == np.float32(-0.01)).all()
    infos = env.step(still)[GRID]
    assert infos.done.sum() == 9 and infos.max_step_reached[infos.done].all()
    np.testing.assert_array_equal(infos.agent_id, np.tile(np.arange(9), 2))  # ids are kept


def test_gridworld_parameters_change_the_layout() -> None:
    env = make("GridWorld", seed=1, gridSize=7, numGreenGoals=3, numRedGoals=2)
    infos = env.reset()[GRID]
    for image in infos.obs[0]:
        cells = decode(image, 7)
        assert (cells[0] == WALL).all() and (cells[:, -1] == WALL).all()
        inside = cells[1:-1, 1:-1]
        assert [(inside == code).sum() for code in (WALL, GREEN, RED, AGENT)] == [0, 3, 2, 1]
    positions: set[tuple[int, int]] = set()
    rng = np.random.default_rng(0)
    out = {GRID: infos}
    for _ in range(40):
        positions |= check_masks(out[GRID], 7)
        out = env.step(random_actions(env, out, rng))
    assert max(max(p) for p in positions) == 6  # the grid is 7 x 7 now
