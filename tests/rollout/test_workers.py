"""Rollout workers on real Ray over unitysim's environments: agents that come and go,
switch behaviors, two behaviors, masks and hybrid actions, the players' priority, and Unity's
custom statistics on their way to the driver."""

from __future__ import annotations

import os

import psutil
import pytest
import torch

from batches import keys
from driver.training.counting_learner import CountingLearner
from learners.acting.factory import actor_factory
from rollout.environment.unity import UnityConfig
from rollout.serving.metrics import StatsAggregationMethod
from rollout.serving.service import RolloutService
from tests.helpers import trajectories
from tests.rollout.workers import collect, service_config, start_worker, stop_worker

pytestmark = pytest.mark.integration


def test_dungeon_escape_agents_come_and_go(ray_session, registry):
    worker = start_worker(ray_session, registry, "unitysim:DungeonEscape", horizon=16)
    segments, newest = [], 0
    try:
        for _ in range(300):  # a room resets (bringing agents back with new ids) in ~500 steps
            segments += collect(ray_session, worker, 1)
            newest = max(newest, int(segments[-1][keys.AGENT_ID].max()))
            if newest >= 36:
                break
    finally:
        stop_worker(ray_session, worker)
    ids = torch.cat([s[keys.AGENT_ID] for s in segments])
    assert int(ids.max()) >= 36, "new agents appeared after the first 36"
    for segment in segments:  # departed agents' rows end at their terminal step, unpadded
        for part in trajectories(segment):
            assert (segment[keys.AGENT_ID][part] == segment[keys.AGENT_ID][part.start]).all()
    group_rewards = torch.cat([s[keys.NEXT, keys.GROUP_REWARD] for s in segments])
    assert group_rewards.shape[0] == ids.shape[0]


def test_workers_and_their_players_run_at_the_launchers_priority(ray_session, registry):
    """Local mode starts Ray's workers at our niceness, not Ray's default 15, and the
    Unity player inherits it: a training run does not yield its CPU to everything else."""
    worker = start_worker(ray_session, registry, "unitysim:3DBall")
    try:
        collect(ray_session, worker, 1)
        identity = ray_session.get(worker.identity.remote())
        niceness = {psutil.Process(identity[k]).nice() for k in ("pid", "player_pid")}
    finally:
        stop_worker(ray_session, worker)
    assert niceness == {os.nice(0)}


def test_walljump_agents_switch_behaviors(ray_session, registry):
    """An agent whose new episode draws the other wall acts on under the other behavior.
    The switch needs an episode end and a redraw, after 4-24 collects in 20 runs (the
    policy samples at random): collect until both are seen, on a budget of collects."""
    worker = start_worker(ray_session, registry, "unitysim:WallJump", horizon=16)
    by_behavior: dict[str, set[int]] = {}
    done = 0
    try:
        for _ in range(300):
            for segment in collect(ray_session, worker, 1):
                ids = set(segment[keys.AGENT_ID].tolist())
                by_behavior.setdefault(segment.get_non_tensor(keys.BEHAVIOR), set()).update(ids)
                done += int(segment[keys.NEXT, keys.TERMINATED].sum())
            if done and len(by_behavior) == 2 and set.intersection(*by_behavior.values()):
                break
        metrics = ray_session.get(worker.metrics.remote())
    finally:
        stop_worker(ray_session, worker)
    assert set(by_behavior) == {"SmallWallJump?team=0", "BigWallJump?team=0"}
    assert by_behavior["SmallWallJump?team=0"] & by_behavior["BigWallJump?team=0"], (
        "no agent id acted under both behaviors in 300 collects"
    )
    assert done > 0, "the old behavior's trajectory ended before the switch"
    assert metrics.dropped_steps == 0


def test_soccer_two_behaviors_and_gridworld_masks(ray_session, registry):
    soccer = start_worker(ray_session, registry, "unitysim:SoccerTwos", horizon=8)
    grid = start_worker(ray_session, registry, "unitysim:GridWorld", horizon=8)
    try:
        soccer_segments = collect(ray_session, soccer, 4)
        grid_segments = collect(ray_session, grid, 10)
    finally:
        stop_worker(ray_session, soccer)
        stop_worker(ray_session, grid)
    assert {s.get_non_tensor(keys.BEHAVIOR) for s in soccer_segments} == {
        "SoccerTwos?team=0",
        "SoccerTwos?team=1",
    }
    masked_choices = 0
    for segment in grid_segments:
        image = segment[keys.OBS, "CameraSensor"]
        assert image.shape[1:] == (3, 40, 40)
        action = segment[keys.ACTION, keys.DISCRETE][..., 0]
        allowed = segment[keys.ACTION_MASK]
        assert torch.gather(allowed, -1, action.unsqueeze(-1))[..., 0].all()
        masked_choices += int((~allowed).sum())
    assert masked_choices > 0, "walls masked some moves, and none of them was sampled"


def test_grid_food_collector_hybrid_actions(ray_session, registry):
    worker = start_worker(ray_session, registry, "unitysim:GridFoodCollector", horizon=8)
    try:
        (segment, *_) = collect(ray_session, worker, 1)
    finally:
        stop_worker(ray_session, worker)
    assert segment[keys.ACTION, keys.CONTINUOUS].shape[-1] == 3
    assert segment[keys.ACTION, keys.DISCRETE].shape[-1] == 1
    assert segment[keys.OBS, "GridSensor-OneHot"].shape[-3:] == (5, 40, 40)
    assert segment[keys.ACTION_MASK].shape[-1] == 2


def test_unity_stats_reach_the_service(ray_session, registry):
    """unitysim's Echo records two statistics per step through the stats side channel."""
    learner = ray_session.remote(CountingLearner).remote()
    config = service_config(UnityConfig("unitysim:Echo"), registry, workers=1)
    with RolloutService(config, actor_factory, learner) as service:
        service.run(agent_steps=300)
        stats = service.metrics.drain_unity_stats()
    assert stats["Echo/Episodes Ended"].method == StatsAggregationMethod.SUM
    assert stats["Echo/Episodes Ended"].value > 0
    assert stats["Echo/Agents Alive"].method == StatsAggregationMethod.MOST_RECENT
