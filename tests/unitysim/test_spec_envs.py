"""The eight spec-faithful unitysim environments, at environment level (no gRPC).

The first ``reset()`` must reproduce the reference dumps' first ``get_steps()`` (behavior
names and order, agent and group ids, sensors, masks; WallJump's 24 terminal infos), and
random play must keep the contract: finite observations of stable shapes, masks of the
right width, one action row per decision row, terminal rows before decisions, episodes
that end, and the same outputs for the same seed and actions. Their rules, driven by
placing things, are tested in ``test_spec_env_rules.py``.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from tests.unitysim.reference import REFERENCE
from unitysim.envs import load
from unitysim.envs.base import (
    DEFAULT_OBS,
    GOAL_SIGNAL,
    Actions,
    AgentInfos,
    Output,
    Parameters,
    SimEnv,
)

SPEC_ENVS = [
    "StrikersVsGoalie",
    "SoccerTwos",
    "Walker",
    "Hallway",
    "Pyramids",
    "DungeonEscape",
    "GridFoodCollector",
    "WallJump",
]
# with no reference dump: laid out from the examples' C# and prefabs
CONTRACT_ENVS = [
    *SPEC_ENVS,
    *("Sorter", "Match3", "Visual3DBall", "PushBlock", "PushBlockCollab", "VisualFoodCollector"),
    *("Crawler", "Worm"),
]
OBSERVATION_TYPES = {"DEFAULT": DEFAULT_OBS, "GOAL_SIGNAL": GOAL_SIGNAL}


def make(name: str, seed: int = 0, num_areas: int = 1) -> SimEnv:
    return load(name)(np.random.default_rng(seed), num_areas, Parameters())


def random_actions(env: SimEnv, output: Output, rng: np.random.Generator) -> dict[str, Actions]:
    """Uniform actions for the decision rows of ``output``, never a masked one."""
    actions = {}
    for behavior in env.behaviors:
        infos = output[behavior.name]
        decide = ~infos.done
        k = int(decide.sum())
        continuous = rng.uniform(-1.0, 1.0, (k, behavior.continuous)).astype(np.float32)
        discrete = np.zeros((k, len(behavior.branches)), dtype=np.int32)
        if behavior.branches:
            mask = infos.action_mask[decide]
            first = 0
            for branch, size in enumerate(behavior.branches):
                scores = rng.random((k, size))
                scores[mask[:, first : first + size]] = -1.0
                discrete[:, branch] = scores.argmax(axis=1)
                first += size
        actions[behavior.name] = Actions(continuous, discrete)
    return actions


def play(env: SimEnv, steps: int, seed: int = 1) -> Iterator[Output]:
    """The reset output, then ``steps`` outputs of random play."""
    rng = np.random.default_rng(seed)
    output = env.reset()
    yield output
    for _ in range(steps):
        output = env.step(random_actions(env, output, rng))
        yield output


def check_batch(env: SimEnv, output: Output) -> None:
    """Shapes, dtypes, finiteness, masks and row order of one output."""
    assert list(output) == [b.name for b in env.behaviors]
    for behavior in env.behaviors:
        infos: AgentInfos = output[behavior.name]
        n = len(infos)
        assert infos.agent_id.dtype == np.int32 and infos.group_id.dtype == np.int32
        for sensor, obs in zip(behavior.sensors, infos.obs, strict=True):
            assert obs.shape == (n, *sensor.shape), (behavior.name, sensor.name)
            assert obs.dtype == np.float32
            assert np.isfinite(obs).all(), (behavior.name, sensor.name)
            if sensor.png:
                assert obs.min(initial=0.0) >= 0.0 and obs.max(initial=0.0) <= 1.0
                if not sensor.rendered:  # a grid's one-hot: one channel per cell at most
                    assert (obs.sum(axis=1) <= 1.0).all()
        assert np.isfinite(infos.reward).all() and np.isfinite(infos.group_reward).all()
        if behavior.branches:
            assert infos.action_mask is not None
            assert infos.action_mask.shape == (n, behavior.mask_size)
            assert infos.action_mask.dtype == np.bool_
            decide = ~infos.done
            for branch in np.split(infos.action_mask[decide], np.cumsum(behavior.branches)[:-1], 1):
                assert not branch.all(axis=1).any(), "a branch with every action masked"
        else:
            assert infos.action_mask is None
        # terminal rows first; at most one decision row per agent
        assert not (infos.done[1:] & ~infos.done[:-1]).any()
        decided = infos.agent_id[~infos.done]
        assert len(np.unique(decided)) == len(decided)
        assert not infos.max_step_reached[~infos.done].any()


@pytest.mark.parametrize("name", SPEC_ENVS)
def test_first_reset_matches_reference(name):
    reference = REFERENCE[name]
    env = make(name)
    assert env.name == name
    assert [b.name for b in env.behaviors] == list(reference)
    output = env.reset()
    check_batch(env, output)
    assert list(output) == list(reference)
    for behavior in env.behaviors:
        expected = reference[behavior.name]
        assert [
            (s.name, s.shape, s.dimension_properties, s.observation_type) for s in behavior.sensors
        ] == [
            (s.name, s.shape, s.dimension_property, OBSERVATION_TYPES[s.observation_type])
            for s in expected.sensors
        ]
        assert (behavior.continuous, behavior.branches) == (expected.continuous, expected.branches)
        infos = output[behavior.name]
        decide, done = ~infos.done, infos.done
        assert infos.agent_id[decide].tolist() == expected.decision.agent_id
        assert infos.group_id[decide].tolist() == expected.decision.group_id
        assert [o[decide].shape for o in infos.obs] == expected.decision.observation_shapes
        assert infos.agent_id[done].tolist() == expected.terminal.agent_id
        assert infos.group_id[done].tolist() == expected.terminal.group_id
        assert [o[done].shape for o in infos.obs] == expected.terminal.observation_shapes
        if expected.decision.action_mask_shapes is not None:
            widths = [shape[1] for shape in expected.decision.action_mask_shapes]
            assert infos.action_mask[decide].shape == (int(decide.sum()), sum(widths))
        assert infos.max_step_reached[done].all()  # only WallJump has any: all interrupted
        assert (infos.reward == 0).all() and (infos.group_reward == 0).all()


@pytest.mark.parametrize("name", CONTRACT_ENVS)
def test_random_play_keeps_the_contract_and_episodes_end(name):
    env = make(name)
    running: dict[int, str] = {}  # agent id -> behavior of its running episode
    done_rows = step = 0
    for step, output in enumerate(play(env, 1500)):
        check_batch(env, output)
        for behavior, infos in output.items():  # terminal rows close episodes ...
            for agent in infos.agent_id[infos.done].tolist():
                assert running.pop(agent, behavior) == behavior
            done_rows += int(infos.done.sum()) if step else 0
        for behavior, infos in output.items():  # ... decisions open or continue them
            for agent in infos.agent_id[~infos.done].tolist():
                assert running.setdefault(agent, behavior) == behavior, (
                    f"agent {agent} asks under {behavior} while running under another"
                )
        if step >= 300 and done_rows:
            break
    assert done_rows > 0, f"no episode ended in {step} steps"


@pytest.mark.parametrize("name", CONTRACT_ENVS)
def test_same_seed_and_actions_give_the_same_outputs(name):
    first, second = (play(make(name, seed=7), 150, seed=3) for _ in range(2))
    for a, b in zip(first, second, strict=True):
        for behavior in a:
            x, y = a[behavior], b[behavior]
            for field in ("agent_id", "reward", "done", "max_step_reached", "group_id"):
                np.testing.assert_array_equal(getattr(x, field), getattr(y, field))
            np.testing.assert_array_equal(x.group_reward, y.group_reward)
            for ox, oy in zip(x.obs, y.obs, strict=True):
                np.testing.assert_array_equal(ox, oy)
            if x.action_mask is not None:
                np.testing.assert_array_equal(x.action_mask, y.action_mask)
    other = make(name, seed=8).reset()
    assert any(
        not np.array_equal(o1, o2)
        for behavior in other
        for o1, o2 in zip(
            other[behavior].obs, make(name, seed=7).reset()[behavior].obs, strict=True
        )
    )


@pytest.mark.parametrize("name", CONTRACT_ENVS)
def test_num_areas_replicates_the_areas(name):
    one, two = make(name).reset(), make(name, num_areas=2).reset()
    ids = np.concatenate([infos.agent_id for infos in two.values()])
    for behavior in one:
        a, b = one[behavior], two[behavior]
        assert len(b) == 2 * len(a)
        assert int((~b.done).sum()) == 2 * int((~a.done).sum())
        # the first area keeps its ids and groups; the second continues both
        first = np.isin(b.agent_id, a.agent_id)
        np.testing.assert_array_equal(b.agent_id[first], a.agent_id)
        np.testing.assert_array_equal(b.group_id[first], a.group_id)
        assert (b.agent_id[~first] > max(a.agent_id.max(), 0)).all()
        if a.group_id.max() > 0:
            assert b.group_id[~first].min() > a.group_id.max()
    assert sorted(set(ids.tolist())) == list(range(len(set(ids.tolist()))))


def test_actions_must_match_the_decision_rows():
    env = make("SoccerTwos")
    output = env.reset()
    actions = random_actions(env, output, np.random.default_rng(0))
    name = env.behaviors[0].name
    short = Actions(actions[name].continuous[1:], actions[name].discrete[1:])
    with pytest.raises(ValueError, match="decision rows"):
        env.step({**actions, name: short})


def test_dungeon_escape_agents_disappear_and_come_back_with_new_ids():
    env = make("DungeonEscape")
    members: dict[int, set[int]] = {}  # group -> agents that asked for a decision last
    sacrificed: set[int] = set()
    fewer = False
    highest = 35
    for output in play(env, 3000):
        infos = output["DungeonEscape?team=0"]
        deciding = infos.agent_id[~infos.done]
        assert not sacrificed & set(deciding.tolist()), "a sacrificed agent came back"
        for group in np.unique(infos.group_id[infos.done]).tolist():
            ended = set(infos.agent_id[infos.done & (infos.group_id == group)].tolist())
            if ended < members.get(group, set()):  # the rest of the group plays on
                sacrificed |= ended
        for group in np.unique(infos.group_id[~infos.done]).tolist():
            members[group] = set(infos.agent_id[~infos.done & (infos.group_id == group)].tolist())
        newcomers = deciding[deciding > highest]
        if len(newcomers):  # new agents get ids never used before
            assert newcomers.min() == highest + 1
            highest = int(newcomers.max())
        fewer |= bool(infos.done.sum() == 0 and 0 < len(deciding) < 36)
        if sacrificed and fewer and highest > 40:
            break
    assert sacrificed, "no agent was sacrificed"
    assert fewer, "agents never went missing from the decisions"
    assert highest > 40, "agents did not come back with new ids"


def test_walljump_agents_switch_behaviors_through_terminal_infos():
    env = make("WallJump")
    last: dict[int, str] = {}
    switched = set()
    jump_masked = False
    for output in play(env, 1500):
        for behavior, infos in output.items():
            for agent in infos.agent_id[~infos.done].tolist():
                if last.get(agent, behavior) != behavior:
                    switched.add(agent)
                last[agent] = behavior
            if len(infos):
                jump_masked |= bool(infos.action_mask[~infos.done, -1].any())
        if len(switched) >= 5 and jump_masked:
            break
    assert len(switched) >= 5
    assert jump_masked, "jumping was never masked in the air"


def test_walljump_later_reset_reports_only_agents_that_switch():
    env = make("WallJump")
    first = env.reset()
    assert int(first["SmallWallJump?team=0"].done.sum()) == 24
    before = {a: b for b, infos in first.items() for a in infos.agent_id[~infos.done].tolist()}
    second = env.reset()
    check_batch(env, second)
    after = {a: b for b, infos in second.items() for a in infos.agent_id[~infos.done].tolist()}
    reported = {(a, b) for b, infos in second.items() for a in infos.agent_id[infos.done].tolist()}
    assert reported == {(a, before[a]) for a in after if after[a] != before[a]}
    assert all(infos.max_step_reached[infos.done].all() for infos in second.values())


def test_terminal_and_decision_in_one_message_at_max_step():
    env = make("GridFoodCollector")
    for output in play(env, 600):
        infos = output["GridFoodCollector?team=0"]
        if infos.done.any():
            assert infos.max_step_reached[infos.done].all()
            np.testing.assert_array_equal(infos.agent_id[infos.done], infos.agent_id[~infos.done])
            return
    pytest.fail("no MaxStep within 600 steps")
