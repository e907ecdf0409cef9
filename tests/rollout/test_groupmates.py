"""Each transition's groupmates, against what ML-Agents' agent processor records for POCA:
built from mlagents_envs' own DecisionSteps and TerminalSteps."""

from __future__ import annotations

import numpy as np
from mlagents_envs.base_env import DecisionSteps, TerminalSteps

from batches import keys
from batches.segment import Segment
from rollout.collecting.decisions import Decisions
from rollout.collecting.segments import SegmentBuilder
from testkit.segments import vector_spec

SPEC = vector_spec(2, continuous=1)
GROUP = {1: 1, 2: 1, 3: 1, 4: 0}  # agent -> group; agent 4 plays alone


def obs_of(agents: list[int], exchange: int) -> list[np.ndarray]:
    """Agent a at exchange e sees (100 a + e, e)."""
    return [np.array([[100 * a + exchange, exchange] for a in agents], np.float32)]


def decisions(agents: list[int], exchange: int) -> DecisionSteps:
    n = len(agents)
    return DecisionSteps(
        obs_of(agents, exchange),
        np.full(n, 0.5, np.float32),
        np.array(agents, np.int32),
        None,
        [GROUP[a] for a in agents],  # a list, as mlagents_envs builds it from the wire
        np.zeros(n, np.float32),
    )


def terminals(agents: list[int], exchange: int) -> TerminalSteps:
    n = len(agents)
    return TerminalSteps(
        obs_of(agents, exchange),
        np.full(n, -1.0, np.float32),
        np.zeros(n, np.bool_),
        np.array(agents, np.int32),
        [GROUP[a] for a in agents],  # a list, as mlagents_envs builds it from the wire
        np.zeros(n, np.float32),
    )


def act(builder: SegmentBuilder, steps: DecisionSteps, exchange: int) -> None:
    """Agent a's action at exchange e is 10 a + e."""
    n = len(steps)
    continuous = (steps.agent_id * 10 + exchange).astype(np.float32)[:, None]
    chosen = Decisions(continuous, np.zeros((n, 0), np.int64), np.zeros((n, 1), np.float32))
    builder.act(steps, chosen, policy_version=0)


def play() -> Segment:
    """Agents 1-3 in group 1, agent 4 alone; agent 3 leaves the group (its episode ends)
    at exchange 2, the others play on; rows are cut at 3 transitions."""
    builder = SegmentBuilder("Knights?team=0", SPEC, horizon=3)
    everyone = [1, 2, 3, 4]
    script = [(everyone, []), (everyone, []), ([1, 2, 4], [3]), ([1, 2, 4], [])]
    parts = []
    for exchange, (deciding, ending) in enumerate(script):
        step = decisions(deciding, exchange)
        ended = terminals(ending, exchange) if ending else TerminalSteps.empty(SPEC)
        builder.observe(step, ended)
        if (segment := builder.collect()) is not None:
            parts.append(segment)
        act(builder, step, exchange)
    return Segment.concat(parts)


def steps_of(segment: Segment, agent: int) -> list[int]:
    return np.flatnonzero(segment.data[keys.AGENT_ID] == agent).tolist()


def mates(segment: Segment, row: int) -> dict[int, tuple[float, float, float, bool]]:
    """The groupmates of one step: agent -> (obs acted on, action, next obs, done)."""
    g, after = segment.data[keys.GROUPMATES], segment.data[keys.NEXT][keys.GROUPMATES]
    found = {}
    for place in np.flatnonzero(g[keys.PRESENT][row]):
        obs = g[keys.OBS]["vector"][row, place]
        agent = int(obs[0] // 100)
        found[agent] = (
            float(obs[0]),
            float(g[keys.ACTION][keys.CONTINUOUS][row, place, 0]),
            float(after[keys.OBS]["vector"][row, place, 0]),
            bool(g[keys.DONE][row, place]),
        )
    return found


def test_each_step_carries_its_groupmates_statuses_as_ml_agents_records_them():
    segment = play()
    assert segment.data[keys.GROUPMATES][keys.PRESENT].shape == (len(segment), 2)
    first, second, third = steps_of(segment, 1)
    # the decision both acted on at exchange 0, the action, and what each sees at exchange 1
    assert mates(segment, first) == {2: (200, 20, 201, False), 3: (300, 30, 301, False)}
    # agent 3's episode ends at exchange 2: its last status is there, done, for that step
    assert mates(segment, second) == {2: (201, 21, 202, False), 3: (301, 31, 302, True)}
    # ... and it is gone afterwards
    assert mates(segment, third) == {2: (202, 22, 203, False)}
    # ML-Agents sets the ending agents' statuses before the others report: agent 3's last
    # step sees its mates as they were one exchange before
    (last,) = steps_of(segment, 3)[-1:]
    assert segment.data[keys.NEXT][keys.DONE][last, 0]
    assert mates(segment, last) == {1: (100, 10, 101, False), 2: (200, 20, 201, False)}


def test_an_agent_outside_any_group_has_no_groupmates():
    segment = play()
    for row in steps_of(segment, 4):
        assert not segment.data[keys.GROUPMATES][keys.PRESENT][row].any()
        assert not segment.data[keys.GROUPMATES][keys.OBS]["vector"][row].any()


def test_a_behavior_without_groups_carries_no_groupmate_places():
    builder = SegmentBuilder("Solo?team=0", SPEC, horizon=2)
    segments = []
    for exchange in range(3):
        step = decisions([4], exchange)
        builder.observe(step, TerminalSteps.empty(SPEC))
        segments.append(builder.collect())
        act(builder, step, exchange)
    segment = segments[-1]
    assert segment is not None
    assert segment.data[keys.GROUPMATES][keys.OBS]["vector"].shape == (2, 0, 2)


def test_segments_with_more_groupmates_later_concatenate_padded():
    narrow = play()
    assert narrow.data[keys.GROUPMATES][keys.PRESENT].shape[1] == 2
    short = Segment(narrow.behavior, narrow.spec, _first_places(narrow.data, 1))
    joined = Segment.concat([short, narrow])
    assert joined.data[keys.GROUPMATES][keys.PRESENT].shape == (2 * len(narrow), 2)
    assert not joined.data[keys.GROUPMATES][keys.PRESENT][: len(narrow), 1].any()


def _first_places(tree: dict, m: int) -> dict:
    out = {}
    for key, value in tree.items():
        if key == keys.GROUPMATES:
            out[key] = _cut(value, m)
        elif isinstance(value, dict):
            out[key] = _first_places(value, m)
        else:
            out[key] = value
    return out


def _cut(tree: dict, m: int) -> dict:
    return {k: _cut(v, m) if isinstance(v, dict) else v[:, :m] for k, v in tree.items()}
