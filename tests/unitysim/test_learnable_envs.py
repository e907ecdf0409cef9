"""Basic, GridWorld and Echo at the environment level (plain numpy, no gRPC).

The contract for all three, then the rules of Basic and Echo; GridWorld's rules are tested
in ``test_gridworld.py``. The helpers here (``make``, ``random_actions``, ``check_infos``,
``run``) serve the other environment-level tests too.
"""

from __future__ import annotations

import numpy as np
import pytest

from unitysim.envs import load
from unitysim.envs.base import Actions, AgentInfos, Output, Parameters, SimEnv

NAMES = ("Basic", "GridWorld", "Echo")
AGENTS = {"Basic": 1, "GridWorld": 9, "Echo": 4}


def make(name: str, seed: int = 0, num_areas: int = 1, **params: float) -> SimEnv:
    return load(name)(np.random.default_rng(seed), num_areas, Parameters(dict(params)))


def decisions(infos: AgentInfos) -> np.ndarray:
    return ~infos.done


def random_actions(env: SimEnv, out: Output, rng: np.random.Generator) -> dict[str, Actions]:
    """Uniform actions over the allowed ones, for every decision row."""
    actions = {}
    for name, infos in out.items():
        behavior = env.behavior(name)
        rows = decisions(infos)
        n = int(rows.sum())
        mask = infos.action_mask[rows]
        discrete, start = [], 0
        for size in behavior.branches:
            allowed = ~mask[:, start : start + size]
            discrete.append(np.argmax(rng.random((n, size)) * allowed, axis=1))
            start += size
        actions[name] = Actions(
            rng.uniform(-1, 1, (n, behavior.continuous)).astype(np.float32),
            np.array(discrete, dtype=np.int32).reshape(len(discrete), n).T,
        )
    return actions


def check_infos(env: SimEnv, out: Output) -> None:
    """The contract: names, shapes, dtypes, masks and finite observations."""
    for name, infos in out.items():
        behavior = env.behavior(name)
        n = len(infos)
        assert infos.agent_id.dtype == np.int32 and infos.agent_id.shape == (n,)
        assert len(infos.obs) == len(behavior.sensors)
        for obs, sensor in zip(infos.obs, behavior.sensors, strict=True):
            assert obs.dtype == np.float32 and obs.shape == (n, *sensor.shape)
            assert np.isfinite(obs).all()
            if sensor.png:
                assert obs.min() >= 0.0 and obs.max() <= 1.0
        for array, dtype in [
            (infos.reward, np.float32),
            (infos.done, np.bool_),
            (infos.max_step_reached, np.bool_),
            (infos.group_id, np.int32),
            (infos.group_reward, np.float32),
        ]:
            assert array.dtype == dtype and array.shape == (n,)
        assert infos.action_mask is not None
        assert infos.action_mask.shape == (n, behavior.mask_size)
        ids = infos.agent_id[decisions(infos)]
        assert len(set(ids.tolist())) == len(ids), "two decision rows for one agent"


def run(env: SimEnv, steps: int, seed: int = 1) -> list[Output]:
    rng = np.random.default_rng(seed)
    outputs = [env.reset()]
    for _ in range(steps):
        outputs.append(env.step(random_actions(env, outputs[-1], rng)))
    return outputs


# --- all three -------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_first_reset(name: str) -> None:
    env = make(name)
    out = env.reset()
    check_infos(env, out)
    assert set(out) <= {b.name for b in env.behaviors}
    assert sum(len(infos) for infos in out.values()) == AGENTS[name]
    assert not any(infos.done.any() for infos in out.values())
    assert all((infos.reward == 0).all() for infos in out.values())


@pytest.mark.parametrize("name", NAMES)
def test_num_areas_multiplies_agents(name: str) -> None:
    out = make(name, num_areas=2).reset()
    assert sum(len(infos) for infos in out.values()) == 2 * AGENTS[name]


@pytest.mark.parametrize("name", NAMES)
def test_deterministic_by_seed(name: str) -> None:
    first, second = run(make(name, seed=3), 150), run(make(name, seed=3), 150)
    for a, b in zip(first, second, strict=True):
        assert a.keys() == b.keys()
        for key in a:
            for field in ("agent_id", "reward", "done", "max_step_reached", "action_mask"):
                np.testing.assert_array_equal(getattr(a[key], field), getattr(b[key], field))
            for x, y in zip(a[key].obs, b[key].obs, strict=True):
                np.testing.assert_array_equal(x, y)
    for out in first:
        check_infos(make(name), out)
    if name != "Basic":  # Basic has no randomness
        other = run(make(name, seed=4), 150)
        assert any(
            a.keys() != b.keys()
            or any(not np.array_equal(a[k].obs[0], b[k].obs[0]) for k in a if k in b)
            for a, b in zip(first, other, strict=True)
        )


# --- Basic -----------------------------------------------------------------------------

BASIC = "Basic?team=0"


def basic_step(env: SimEnv, action: int) -> AgentInfos:
    return env.step({BASIC: Actions(np.zeros((1, 0), np.float32), np.array([[action]]))})[BASIC]


def test_basic_large_goal_in_seven_steps() -> None:
    env = make("Basic")
    first = env.reset()[BASIC]
    np.testing.assert_array_equal(first.obs[0][0], np.eye(20, dtype=np.float32)[10])
    assert not first.action_mask.any()
    episode_return = float(first.reward[0])
    for _ in range(6):
        infos = basic_step(env, 2)
        assert len(infos) == 1 and not infos.done[0] and infos.agent_id[0] == 0
        assert infos.reward[0] == np.float32(-0.01)
        episode_return += float(infos.reward[0])
    infos = basic_step(env, 2)
    np.testing.assert_array_equal(infos.agent_id, [0, 1])
    np.testing.assert_array_equal(infos.done, [True, False])
    assert not infos.max_step_reached.any()
    np.testing.assert_array_equal(infos.obs[0], np.eye(20, dtype=np.float32)[[17, 10]])
    assert infos.reward[0] == np.float32(-0.01) + np.float32(1.0)
    assert infos.reward[1] == 0.0
    episode_return += float(infos.reward[0])
    assert episode_return == pytest.approx(0.93, abs=1e-6)


def test_basic_small_goal_and_new_ids() -> None:
    env = make("Basic")
    env.reset()
    ends = []
    for _ in range(4):  # three steps left reach the small goal, each time with a new agent
        for _ in range(3):
            infos = basic_step(env, 1)
        assert infos.done[0] and infos.reward[0] == np.float32(-0.01) + np.float32(0.1)
        ends.append(tuple(infos.agent_id.tolist()))
    assert ends == [(0, 1), (1, 2), (2, 3), (3, 4)]
    infos = basic_step(env, 0)  # staying costs and ends nothing
    assert not infos.done.any() and infos.reward[0] == np.float32(-0.01)


def test_basic_areas_get_distinct_ids() -> None:
    env = make("Basic", num_areas=3)
    out = env.reset()[BASIC]
    np.testing.assert_array_equal(out.agent_id, [0, 1, 2])
    actions = Actions(np.zeros((3, 0), np.float32), np.array([[2], [1], [0]]))
    for _ in range(3):
        infos = env.step({BASIC: actions})[BASIC]
    np.testing.assert_array_equal(infos.agent_id, [1, 0, 3, 2])  # terminal row, then decisions
    np.testing.assert_array_equal(infos.done, [True, False, False, False])


# --- Echo ------------------------------------------------------------------------------

ECHO_A, ECHO_B = "EchoA?team=0", "EchoB?team=0"


def test_echo_layout_and_masks() -> None:
    env = make("Echo")
    out = env.reset()
    assert set(out) == {ECHO_A, ECHO_B}
    for index, name in enumerate((ECHO_A, ECHO_B)):
        infos = out[name]
        assert env.behavior(name).continuous == 2 and env.behavior(name).branches == (3, 2)
        obs = infos.obs[0]
        np.testing.assert_array_equal(obs[:, 0], infos.agent_id)
        assert (obs[:, 1:7] == 0).all() and (obs[:, 7] == index).all()
        expected = np.zeros((len(infos), 5), dtype=bool)
        expected[:, 2] = infos.agent_id % 2 == 1
        np.testing.assert_array_equal(infos.action_mask, expected)
    with pytest.raises(ValueError, match="actions for"):
        env.step({ECHO_A: Actions.empty(env.behavior(ECHO_A), 7)})


def test_echo_actions_reach_their_agents() -> None:
    env = make("Echo", seed=7)
    rng = np.random.default_rng(0)
    out = env.reset()
    sent: dict[int, tuple[int, np.ndarray]] = {}  # id -> (episode, action echo)
    seen: dict[int, tuple[int, int]] = {}  # id -> (episode, behavior) of its latest row
    events = dict.fromkeys(
        ["end+decision", "switch", "interrupted", "ended", "skip", "leave", "new id"], 0
    )
    counts = {ECHO_A: 0, ECHO_B: 0}
    for _ in range(400):
        check_infos(env, out)
        rows_by_id: dict[int, list[tuple[str, bool]]] = {}
        for name, infos in out.items():
            counts[name] += int(decisions(infos).sum())
            for row, agent in enumerate(infos.agent_id.tolist()):
                obs = infos.obs[0][row]
                episode, step = int(obs[1]), int(obs[2])
                assert obs[0] == agent and obs[7] == (name == ECHO_B)
                assert infos.reward[row] == np.float32(0.01 * step)
                echo = obs[3:7]
                if agent in sent and sent[agent][0] == episode:
                    np.testing.assert_array_equal(echo, sent[agent][1])
                else:
                    assert (echo == 0).all()
                    if agent not in seen:
                        events["new id"] += agent >= 4
                seen[agent] = (episode, name == ECHO_B)
                rows_by_id.setdefault(agent, []).append((name, row, bool(infos.done[row])))
                if infos.done[row]:
                    events["ended"] += 1
                    events["interrupted"] += bool(infos.max_step_reached[row])
        for rows in rows_by_id.values():
            assert len(rows) <= 2
            if len(rows) == 2:  # one terminal row and one decision row, terminal first
                (done_name, done_row, _), (name, row, _) = sorted(rows, key=lambda r: not r[2])
                assert rows[0][2] != rows[1][2]
                if done_name == name:
                    assert done_row < row
                    events["end+decision"] += 1
                else:
                    events["switch"] += 1
        events["skip"] += sum(
            agent not in rows_by_id for agent in env.ids[env.alive].tolist() if agent in sent
        )
        actions = random_actions(env, out, rng)
        for name, act in actions.items():
            infos = out[name]
            for k, row in enumerate(np.flatnonzero(decisions(infos))):
                agent, episode = int(infos.agent_id[row]), int(infos.obs[0][row][1])
                if agent % 2 == 1:
                    assert act.discrete[k, 0] != 2
                echo = np.concatenate([act.continuous[k], act.discrete[k].astype(np.float32)])
                sent[agent] = (episode, echo)
        out = env.step(actions)
    events["leave"] = len(seen) - int(env.alive.sum())
    assert all(count > 0 for count in events.values()), events
    assert counts[ECHO_A] > 0 and counts[ECHO_B] > 0


def test_echo_switch_keeps_the_id_across_behaviors() -> None:
    env = make("Echo", seed=0, switch_prob=1.0, end_prob=0.0, skip_prob=0.0, spawn_prob=0.0)
    env.reset()
    actions = {
        name: Actions(np.full((2, 2), 0.5, np.float32), np.ones((2, 2), np.int32))
        for name in (ECHO_A, ECHO_B)
    }
    out = env.step(actions)
    for name, index in ((ECHO_A, 0), (ECHO_B, 1)):
        infos = out[name]
        assert infos.done.sum() == 2 and infos.max_step_reached[infos.done].all()
        assert (infos.obs[0][infos.done, 3:7] == [0.5, 0.5, 1, 1]).all()  # echoed, then done
        assert (infos.obs[0][infos.done, 7] == index).all()
        assert (infos.obs[0][~infos.done, 7] == index).all()  # switched here from the other
        assert (infos.obs[0][~infos.done, 1:7] == [1, 0, 0, 0, 0, 0]).all()
    moved_to_b = set(out[ECHO_A].agent_id[out[ECHO_A].done].tolist())
    assert moved_to_b == set(out[ECHO_B].agent_id[~out[ECHO_B].done].tolist()) == {0, 2}


def test_echo_late_behavior_and_reset() -> None:
    env = make("Echo", seed=1, start_all_a=1.0)
    out = env.reset()
    assert set(out) == {ECHO_A} and len(out[ECHO_A]) == 4
    outputs = run(env, 100)
    assert any(ECHO_B in o for o in outputs[1:])
    alive = sorted(env.ids[env.alive].tolist())
    episodes = dict(zip(env.ids[env.alive].tolist(), env.episode[env.alive].tolist(), strict=True))
    out = env.reset()  # same agents, new episodes, no terminal rows
    rows = AgentInfos.concat(list(out.values()))
    assert not rows.done.any() and sorted(rows.agent_id.tolist()) == alive
    for obs in rows.obs[0]:
        assert obs[1] == episodes[int(obs[0])] + 1 and (obs[2:7] == 0).all()
