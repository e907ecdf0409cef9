"""Segments checked against ground truth: the Echo environment echoes each agent's last
action into its next observation, so every transition of every row can be verified."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
import torch

from learners.policies import actor_factory
from rollout import keys
from rollout.collector import Collector
from rollout.specs import step_spec
from rollout.unity import UnityConfig
from tests.helpers import leak_checked_allocator

pytestmark = pytest.mark.integration


@pytest.fixture
def allocator(tmp_path):
    with leak_checked_allocator(tmp_path, 24200, 24299) as allocator:
        yield allocator


def check_echo_segment(segment, spec) -> int:
    """Every valid transition is consistent with Echo's rules; returns their number."""
    valid = segment[keys.VALID]
    assert valid.any()
    # Padding only after the last valid step of a row.
    assert torch.equal(valid, valid.cummin(dim=1).values)
    assert step_spec(spec).expand(*segment.batch_size).is_in(segment.exclude(*keys.METADATA))
    nxt = segment[keys.NEXT, keys.OBS, "Echo"]
    obs = segment[keys.OBS, "Echo"]
    action_c = segment[keys.ACTION, keys.CONTINUOUS]
    action_d = segment[keys.ACTION, keys.DISCRETE]
    ids = segment[keys.AGENT_ID]
    # The next observation echoes the action sent to this agent (clipped, as Unity does).
    torch.testing.assert_close(nxt[..., 3:5][valid], action_c.clamp(-1, 1)[valid])
    assert torch.equal(nxt[..., 5:7][valid], action_d.float()[valid])
    assert torch.equal(nxt[..., 0][valid], ids.float()[valid])
    assert torch.equal(obs[..., 0][valid], ids.float()[valid])
    reward = segment[keys.NEXT, keys.REWARD][..., 0]
    torch.testing.assert_close(reward[valid], (0.01 * nxt[..., 2])[valid])
    # Within an episode the next observation is the following step's observation.
    done = segment[keys.NEXT, keys.DONE][..., 0]
    follow = valid[:, 1:] & ~done[:, :-1]
    assert torch.equal(nxt[:, :-1][follow], obs[:, 1:][follow])
    # done = terminated xor truncated; terminated and truncated never both.
    terminated = segment[keys.NEXT, keys.TERMINATED][..., 0]
    truncated = segment[keys.NEXT, keys.TRUNCATED][..., 0]
    assert torch.equal(done, terminated | truncated) and not (terminated & truncated).any()
    # Masked actions are never sampled: odd ids may not pick action 2 of branch 0.
    mask = segment[keys.ACTION_MASK]
    picked = torch.gather(mask[..., :3], -1, action_d[..., :1])[..., 0]
    assert picked[valid].all()
    assert not (action_d[..., 0][valid & (ids % 2 == 1)] == 2).any()
    return int(valid.sum())


def test_echo_rows_are_exact_across_switches_arrivals_and_terminals(allocator):
    collector = Collector(
        UnityConfig("unitysim:Echo", seed=4, num_areas=2),
        actor_factory,
        horizon=16,
        allocator=allocator,
    )
    try:
        checked, padded, behaviors = 0, 0, set()
        for _ in range(40):
            for segment in collector.collect():
                behavior = segment.get_non_tensor(keys.BEHAVIOR)
                behaviors.add(behavior)
                spec = collector.unity.behavior_specs[behavior]
                checked += check_echo_segment(segment, spec)
                padded += int((~segment[keys.VALID]).any(dim=1).sum())
        metrics = collector.snapshot()
    finally:
        collector.close()
    assert behaviors == {"EchoA?team=0", "EchoB?team=0"}
    assert checked > 500
    assert padded > 0, "agents that left or switched behavior end with padded rows"
    assert sum(b.episodes for b in metrics.behaviors.values()) > 10
    assert metrics.dropped_steps == 0


def test_killed_player_restarts_and_no_partial_row_is_emitted(allocator):
    collector = Collector(
        UnityConfig("unitysim:Echo", seed=5, backoff_s=0.0),
        actor_factory,
        horizon=8,
        allocator=allocator,
    )
    try:
        collector.collect()
        old_port, old_pid = collector.unity.port, collector.unity.player_pid
        os.kill(old_pid, signal.SIGKILL)
        segments = []
        for _ in range(10):
            segments += collector.collect()
        metrics = collector.snapshot()
        assert metrics.restarts == 1 and collector.unity.port != old_port
        assert metrics.dropped_steps > 0
        for segment in segments:  # rows mixing pre- and post-crash data would fail here
            check_echo_segment(
                segment, collector.unity.behavior_specs[segment.get_non_tensor(keys.BEHAVIOR)]
            )
    finally:
        collector.close()


def test_3dball_rows_are_full_and_weights_versions_are_stamped(allocator):
    collector = Collector(
        UnityConfig("unitysim:3DBall", seed=1), actor_factory, horizon=10, allocator=allocator
    )
    try:
        first = collector.collect()
        assert len(first) == 1 and first[0].batch_size == torch.Size([12, 10])
        assert first[0][keys.VALID].all()
        assert (first[0][keys.POLICY_VERSION] == 0).all()
        actor = collector.actors["3DBall?team=0"]
        new_state = {k: torch.zeros_like(v) for k, v in actor.state_dict().items()}
        collector.load_weights(3, {"3DBall?team=0": new_state})
        collector.load_weights(2, {"3DBall?team=0": actor.state_dict()})  # older: ignored
        assert all(torch.equal(v, torch.zeros_like(v)) for v in actor.state_dict().values())
        # Rows acted on by version 3 only; at least 24 of them (480 samples): a single row
        # (20 samples) is too few for the statistics below.
        fresh = []
        while sum(segment.batch_size[0] for segment in fresh) < 24:
            fresh += [s for s in collector.collect() if (s[keys.POLICY_VERSION] == 3).all()]
        # Zero weights: the Gaussian mean is 0 and its std 1 for every agent.
        actions = torch.cat([s[keys.ACTION, keys.CONTINUOUS] for s in fresh])
        assert abs(float(actions.mean())) < 0.2 and 0.8 < float(actions.std()) < 1.2
        reward = torch.cat([s[keys.NEXT, keys.REWARD] for s in fresh])
        assert set(np.round(reward.unique().double().numpy(), 3).tolist()) <= {0.1, -1.0}
    finally:
        collector.close()
