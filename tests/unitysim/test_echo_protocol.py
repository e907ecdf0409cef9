"""Through real gRPC, every action reaches the agent it was sampled for: the Echo
environment echoes each agent's last action into its next observation, across appearing
and leaving agents, behavior switches, terminal-and-decision steps and skipped decisions."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from mlagents_envs.base_env import ActionTuple
from mlagents_envs.side_channel.stats_side_channel import StatsSideChannel

pytestmark = pytest.mark.integration
BEHAVIORS = ("EchoA?team=0", "EchoB?team=0")


def check_echo(rows, last_sent: dict, events: Counter, kind: str) -> None:
    """``last_sent[(agent id, episode)]`` is the last action sent to that agent in that
    episode; a row echoes it, or zeros when the agent got no action yet this episode."""
    for obs, agent_id, reward in zip(rows.obs[0], rows.agent_id, rows.reward, strict=True):
        assert obs[0] == agent_id
        assert reward == pytest.approx(0.01 * obs[2], abs=1e-6)
        expected = last_sent.get((int(agent_id), int(obs[1])), np.zeros(4, np.float32))
        np.testing.assert_allclose(obs[3:7], expected, rtol=1e-6)
        events[f"echo-{kind}"] += int(expected.any())


def test_actions_reach_the_right_agents(open_env):
    stats = StatsSideChannel()
    rng = np.random.default_rng(0)
    last_sent: dict[tuple[int, int], np.ndarray] = {}
    events: Counter = Counter()
    seen_ids: set[int] = set()
    with open_env("Echo", seed=3, num_areas=2, side_channels=[stats]) as env:
        env.reset()
        for _ in range(300):
            steps = {b: env.get_steps(b) for b in env.behavior_specs}
            for decisions, terminals in steps.values():  # check everything before acting
                check_echo(terminals, last_sent, events, "terminal")
                check_echo(decisions, last_sent, events, "decision")
                events["terminal+decision"] += len(
                    set(terminals.agent_id) & set(decisions.agent_id)
                )
                events["interrupted"] += int(terminals.interrupted.sum())
                seen_ids |= set(decisions.agent_id.tolist())
            for behavior, (decisions, _) in steps.items():
                n = len(decisions)
                if n == 0:
                    continue
                continuous = rng.uniform(-1, 1, size=(n, 2)).astype(np.float32)
                mask = decisions.action_mask[0]  # branch 0: action 2 forbidden for odd ids
                np.testing.assert_array_equal(mask[:, 2], decisions.agent_id % 2 == 1)
                branch0 = np.where(mask[:, 2], rng.integers(0, 2, n), rng.integers(0, 3, n))
                discrete = np.column_stack([branch0, rng.integers(0, 2, n)]).astype(np.int32)
                env.set_actions(behavior, ActionTuple(continuous=continuous, discrete=discrete))
                for row, agent_id in enumerate(decisions.agent_id):
                    episode = int(decisions.obs[0][row, 1])
                    last_sent[int(agent_id), episode] = np.concatenate(
                        [continuous[row], discrete[row]]
                    )
            env.step()
        received = stats.get_and_reset_stats()
    assert set(env.behavior_specs) == set(BEHAVIORS)
    assert events["echo-decision"] > 500 and events["echo-terminal"] > 20
    assert events["terminal+decision"] > 10 and events["interrupted"] > 5
    assert len(seen_ids) > 8, "new agents appeared"
    assert "Echo/Episodes Ended" in received and "Echo/Agents Alive" in received
