"""Segments checked against ground truth: the Echo environment echoes each agent's last
action into its next observation, so every transition of every row can be verified."""

from __future__ import annotations

import os
import signal
from itertools import pairwise

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from batches import keys
from batches.parameters import Constant
from batches.specs import spec_from_dict, step_spec
from learners.acting.factory import actor_factory
from rollout.collecting.collector import NO_AGENT_STEPS, Collector
from rollout.collecting.horizons import Horizons
from rollout.environment.restarts import RestartPolicy
from rollout.environment.unity import UnityConfig, UnityError, UnityStartError
from tests.helpers import leak_checked_allocator, trajectories

pytestmark = pytest.mark.integration


@pytest.fixture
def allocator(tmp_path):
    with leak_checked_allocator(tmp_path, 24200, 24299) as allocator:
        yield allocator


def check_echo_segment(segment, spec, horizon: int) -> list[tuple[int, int, int, int]]:
    """Every transition is consistent with Echo's rules; returns, per trajectory, (agent,
    episode, its first step index, length)."""
    assert step_spec(spec).expand(*segment.batch_size).is_in(segment.exclude(*keys.METADATA))
    nxt = segment[keys.NEXT, keys.OBS, "Echo"]
    obs = segment[keys.OBS, "Echo"]
    action_c = segment[keys.ACTION, keys.CONTINUOUS]
    action_d = segment[keys.ACTION, keys.DISCRETE]
    ids = segment[keys.AGENT_ID]
    # The next observation echoes the action sent to this agent (ML-Agents' scale).
    torch.testing.assert_close(nxt[:, 3:5], action_c.clamp(-3, 3) / 3)
    assert torch.equal(nxt[:, 5:7], action_d.float())
    assert torch.equal(nxt[:, 0], ids.float()) and torch.equal(obs[:, 0], ids.float())
    reward = segment[keys.NEXT, keys.REWARD][:, 0]
    torch.testing.assert_close(reward, 0.01 * nxt[:, 2])
    # done = terminated xor truncated; terminated and truncated never both.
    done = segment[keys.NEXT, keys.DONE][:, 0]
    terminated = segment[keys.NEXT, keys.TERMINATED][:, 0]
    truncated = segment[keys.NEXT, keys.TRUNCATED][:, 0]
    assert torch.equal(done, terminated | truncated) and not (terminated & truncated).any()
    # Masked actions are never sampled: odd ids may not pick action 2 of branch 0.
    mask = segment[keys.ACTION_MASK]
    picked = torch.gather(mask[:, :3], -1, action_d[:, :1])[:, 0]
    assert picked.all()
    assert not (action_d[:, 0][ids % 2 == 1] == 2).any()
    found = []
    for part in trajectories(segment):
        agent, episode = ids[part], obs[part, 1]
        assert (agent == agent[0]).all() and (episode == episode[0]).all()
        # Within a trajectory the next observation is the following step's observation.
        assert torch.equal(nxt[part][:-1], obs[part][1:])
        length = part.stop - part.start
        assert 1 <= length <= horizon
        found.append((int(agent[0]), int(episode[0]), int(obs[part.start, 2]), length))
    return found


def collect(collector: Collector, min_steps: int = 1) -> list[TensorDict]:
    """A collect call's segments as the learner sees them."""
    return [segment.to_tensordict() for segment in collector.collect(min_steps)]


def test_echo_trajectories_are_exact_across_switches_arrivals_and_terminals(allocator):
    horizon = 16
    collector = Collector(
        UnityConfig("unitysim:Echo", seed=4, num_areas=2),
        actor_factory,
        horizon=horizon,
        allocator=allocator,
    )
    try:
        steps, behaviors, by_agent = 0, set(), {}
        for _ in range(40):
            for segment in collect(collector, 20):
                behavior = segment.get_non_tensor(keys.BEHAVIOR)
                behaviors.add(behavior)
                spec = collector.unity.behavior_specs[behavior]
                for found in check_echo_segment(segment, spec, horizon):
                    by_agent.setdefault(found[0], []).append(found)
                steps += segment.batch_size[0]
        metrics = collector.snapshot()
    finally:
        collector.close()
    assert behaviors == {"EchoA?team=0", "EchoB?team=0"}
    assert steps > 500
    # An agent's trajectories tile each episode (in time order; an agent that switched
    # behavior has its trajectories in two segments): every one that a later one of the
    # same episode continues was cut at exactly the horizon; the others ended the episode.
    cuts = ends = 0
    for found in by_agent.values():
        found.sort(key=lambda t: (t[1], t[2]))
        for (_, episode, first, length), (_, next_episode, next_first, _) in pairwise(found):
            if next_episode == episode:
                assert length == horizon and next_first > first
                cuts += 1
            else:
                ends += length < horizon
    assert cuts > 0 and ends > 10
    assert sum(b.episodes for b in metrics.behaviors.values()) > 10
    assert metrics.dropped_steps == 0


def test_killed_player_restarts_and_no_partial_row_is_emitted(allocator):
    collector = Collector(
        UnityConfig("unitysim:Echo", seed=5, restarts=RestartPolicy(backoff_s=0.0)),
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
            segments += collect(collector)
        metrics = collector.snapshot()
        assert metrics.restarts == 1 and collector.unity.port != old_port
        assert metrics.dropped_steps > 0
        # the ledger's side of the collector: every recorded step is somewhere
        counts = collector.counts()
        assert counts and all(c.lost > 0 for c in counts.values())
        for c in counts.values():
            assert c.produced == c.emitted + c.lost + c.in_progress, c
        emitted = sum(c.emitted for c in counts.values())
        assert emitted >= sum(s.batch_size[0] for s in segments)  # + the first collect's
        for segment in segments:  # rows mixing pre- and post-crash data would fail here
            behavior = segment.get_non_tensor(keys.BEHAVIOR)
            check_echo_segment(segment, collector.unity.behavior_specs[behavior], horizon=8)
    finally:
        collector.close()


def test_3dball_rows_are_cut_at_the_horizon_and_weights_versions_are_stamped(allocator):
    collector = Collector(
        UnityConfig("unitysim:3DBall", seed=1), actor_factory, horizon=10, allocator=allocator
    )
    try:
        first = collect(collector, 1)
        # 12 agents in step from the reset: the first rows are the 12 cut at 10 steps.
        assert len(first) == 1 and first[0].batch_size == torch.Size([120])
        assert [p.stop - p.start for p in trajectories(first[0])] == [10] * 12
        assert first[0][keys.NEXT, keys.TRUNCATED][9::10].all()
        cuts = first[0][keys.NEXT, keys.CUT][:, 0]  # the episodes go on
        assert cuts[9::10].all() and int(cuts.sum()) == 12
        assert (first[0][keys.POLICY_VERSION] == 0).all()
        spec = collector.unity.behavior_specs["3DBall?team=0"]
        initial = actor_factory.initial_weights("3DBall?team=0", spec)
        zeros = {k: np.zeros_like(v) for k, v in initial.items()}
        wide = {**initial, "log_std": np.full_like(initial["log_std"], 2.0)}  # std 7.4
        collector.load_weights(3, {"3DBall?team=0": zeros})
        collector.load_weights(2, {"3DBall?team=0": wide})  # older: ignored
        # Steps acted on by version 3 only; at least 480 of them: 20 are too few for the
        # statistics below.
        fresh = []
        while sum(segment.batch_size[0] for segment in fresh) < 480:
            for segment in collect(collector, 100):
                fresh.append(segment[segment[keys.POLICY_VERSION] == 3])
        # Zero weights: the Gaussian mean is 0 and its std 1 for every agent.
        actions = torch.cat([s[keys.ACTION, keys.CONTINUOUS] for s in fresh])
        assert abs(float(actions.mean())) < 0.2 and 0.8 < float(actions.std()) < 1.2
        reward = torch.cat([s[keys.NEXT, keys.REWARD] for s in fresh])
        assert set(np.round(reward.unique().double().numpy(), 3).tolist()) <= {0.1, -1.0}
    finally:
        collector.close()


def test_a_build_whose_agents_never_ask_for_decisions_is_one_line(allocator):
    """As a build with every agent on Behavior Type "Heuristic Only": the run ends with
    what to check instead of stepping forever without data."""
    config = UnityConfig("unitysim:3DBall", additional_args=("--sim-silent-after", "0"))
    collector = Collector(config, actor_factory, horizon=16, allocator=allocator)
    try:
        with pytest.raises(UnityError, match="no agent asked for a decision in 3000") as error:
            collector.collect(min_steps=1)
        assert "\n" not in str(error.value)
        assert collector.metrics.env_steps == NO_AGENT_STEPS
    finally:
        collector.close()


def test_segments_name_their_source_for_the_learner_to_take_each_once(allocator):
    collector = Collector(
        UnityConfig("unitysim:3DBall", seed=2), actor_factory, horizon=10, allocator=allocator
    )
    try:
        sources = [s.source for _ in range(3) for s in collector.collect(min_steps=1)]
        incarnation = collector.metrics.incarnation
        assert incarnation and sources == [(incarnation, 1), (incarnation, 2), (incarnation, 3)]
    finally:
        collector.close()
    other = Collector(UnityConfig("unitysim:3DBall"), actor_factory, 10, allocator=allocator)
    assert other.metrics.incarnation != incarnation  # a restarted worker: a new source


def test_a_restarted_workers_failed_launch_is_retried_but_a_runs_first_is_final(
    allocator, tmp_path
):
    from unitysim.launcher import build as build_launchers

    (launcher,) = build_launchers(tmp_path / "build", ["3DBall"])
    marker = tmp_path / "launched-once"
    flaky = tmp_path / "Flaky.x86_64"  # dies at its first launch, works after
    flaky.write_text(
        f'#!/bin/sh\nif [ ! -e "{marker}" ]; then touch "{marker}"; exit 0; fi\n'
        f'exec "{launcher}" "$@"\n'
    )
    flaky.chmod(0o755)
    config = UnityConfig(str(flaky), restarts=RestartPolicy(backoff_s=0.0))
    first = Collector(config, actor_factory, horizon=10, allocator=allocator)
    with pytest.raises(UnityStartError, match="exited with code 0 before it connected"):
        first.start()  # a run's first launch: a build that exits is a bad build
    first.close()
    marker.unlink()
    restarted = Collector(config, actor_factory, horizon=10, allocator=allocator)
    try:
        restarted.start(restarted=True)  # Ray's restart of a worker: the build has worked
        assert restarted.unity.restarts == 1
        assert restarted.collect(min_steps=1)
    finally:
        restarted.close()


def slow_build(folder, launches_that_never_connect: int | None):
    """A build whose first launches run but never open their port (a player on a loaded
    node slower than ``timeout_wait``); after them (if not None) the real stand-in."""
    from unitysim.launcher import build as build_launchers

    (launcher,) = build_launchers(folder / "build", ["3DBall"])
    count, path = folder / "launches", folder / "Slow.x86_64"
    works = (
        ""
        if launches_that_never_connect is None
        else (
            f'if [ "$(wc -c < "{count}")" -gt {launches_that_never_connect} ]; then '
            f'exec "{launcher}" "$@"; fi\n'
        )
    )
    path.write_text(f'#!/bin/sh\necho >> "{count}"\n{works}exec tail -f /dev/null\n')
    path.chmod(0o755)
    return path, count


def test_a_runs_first_launch_that_is_slow_to_connect_is_retried(allocator, tmp_path):
    build, launches = slow_build(tmp_path, 1)
    policy = RestartPolicy(backoff_s=0.0)
    config = UnityConfig(str(build), restarts=policy, timeout_wait=10)  # about the timeout
    collector = Collector(config, actor_factory, horizon=10, allocator=allocator)
    try:
        collector.start()  # not restarted: the run's first launch
        # every launch but the last was retried, whatever their number: the stand-in after
        # the slow launch has the same 10 s, which a loaded machine may not give it, and a
        # launch killed at its timeout may not have reached its first line (the count): the
        # one that connected saw two launches counted, and came after every counted one
        launched = launches.read_text().count("\n")
        assert launched >= 2 and collector.unity.restarts >= launched - 1, launched
        assert collector.collect(min_steps=1)
    finally:
        collector.close()


def test_a_build_that_never_connects_gives_up_in_one_line_naming_the_wait(allocator, tmp_path):
    build, _ = slow_build(tmp_path, None)
    policy = RestartPolicy(backoff_s=0.0, max_failed_starts=1)
    config = UnityConfig(str(build), restarts=policy, timeout_wait=1)  # about the timeout
    collector = Collector(config, actor_factory, horizon=10, allocator=allocator)
    try:
        with pytest.raises(UnityError) as error:
            collector.start()
    finally:
        collector.close()
    message = str(error.value)
    assert "\n" not in message and "2 launches in a row failed" in message, message
    assert "did not connect within timeout_wait (1 s)" in message, message


def test_cameras_sent_as_png_reach_the_learner_as_uint8(allocator):
    """GridWorld's camera arrives as PNG: the segments carry it as uint8 0..255 (its
    palette: 0, 128, 255), its goal signal as float32, through the real protocol."""
    collector = Collector(
        UnityConfig("unitysim:GridWorld", seed=2), actor_factory, horizon=8, allocator=allocator
    )
    try:
        segments = collect(collector, 40)
        assert collector.unity.png_sensors("GridWorld?team=0") == {"CameraSensor"}
    finally:
        collector.close()
    batch = torch.cat(segments)
    camera, goal = batch[keys.OBS, "CameraSensor"], batch[keys.OBS, "GoalSignal"]
    assert camera.dtype == torch.uint8 and camera.shape[1:] == (3, 40, 40)
    assert goal.dtype == torch.float32
    assert set(camera.unique().tolist()) <= {0, 128, 255} and camera.max() == 255
    spec = spec_from_dict(batch.get_non_tensor(keys.SPEC))
    assert (
        step_spec(spec, {"CameraSensor"})
        .expand(*batch.batch_size)
        .is_in(batch.exclude(*keys.METADATA))
    )


def test_each_behavior_cuts_its_rows_at_its_own_time_horizon(allocator):
    """Two behaviors, two time horizons (ML-Agents cuts each trainer's trajectories at its
    own): every Striker row ends by 5 steps and every Goalie row by 9, the long ones at
    exactly that."""
    horizons = Horizons(64, {"Striker": 5, "Goalie": 9})
    collector = Collector(
        UnityConfig("unitysim:StrikersVsGoalie", seed=3), actor_factory, horizons, 0, allocator
    )
    try:
        lengths: dict[str, set[int]] = {}
        while len(lengths) < 2 or sum(len(found) for found in lengths.values()) < 4:
            for segment in collect(collector, 200):
                behavior = segment.get_non_tensor(keys.BEHAVIOR)
                rows = trajectories(segment)
                lengths.setdefault(behavior.split("?")[0], set()).update(
                    row.stop - row.start for row in rows
                )
        assert max(lengths["Striker"]) == 5 and max(lengths["Goalie"]) == 9, lengths
    finally:
        collector.close()


def test_a_lesson_with_require_reset_drops_rows_in_progress_and_resets_unity(allocator):
    """As mlagents-learn on a lesson's ``require_reset``: rows in progress are dropped (the
    ledger books them as "lesson reset"), Unity resets, and no episode goes on under the
    old values; without it the values change at the build's next episode resets."""
    unity = UnityConfig("unitysim:3DBall")
    collector = Collector(unity, actor_factory, horizon=1000, allocator=allocator)
    try:
        collect(collector, 1)  # rows of 1000 steps: every agent's row is still in progress
        counts = collector.counts()["3DBall?team=0"]
        assert counts.in_progress > 0 and counts.reset == 0
        collector.set_parameters({"mass": Constant(2.0)}, reset=False)
        assert collector.counts()["3DBall?team=0"].in_progress == counts.in_progress
        collector.set_parameters({"scale": Constant(1.5)}, reset=True)
        after = collector.counts()["3DBall?team=0"]
        assert after.in_progress == 0 and after.reset == counts.in_progress
        assert after.produced == after.emitted + after.lost + after.reset + after.in_progress
        assert collector.unity.parameters == {"mass": Constant(2.0), "scale": Constant(1.5)}
        collect(collector, 1)  # and it goes on collecting
        assert collector.counts()["3DBall?team=0"].produced > after.produced
    finally:
        collector.close()


def test_a_policy_with_memory_carries_each_agents_memory_across_gaps_and_resets_it(allocator):
    """Echo's agents skip decisions, end episodes and switch behaviors: each step stores the
    memory its decision read; an episode's first step reads zeros, and every later one the
    memory the agent's previous decision left (recomputed here with the same actor)."""
    from learners.acting.factory import PolicyFactory
    from learners.trainer_config.settings import MemorySettings, NetworkSettings

    factory = PolicyFactory(default=NetworkSettings(hidden_units=8, memory=MemorySettings(8, 4)))
    collector = Collector(
        UnityConfig("unitysim:Echo", seed=4, num_areas=2), factory, horizon=16, allocator=allocator
    )
    rows: dict[tuple[str, int], list[tuple[float, float, np.ndarray, np.ndarray]]] = {}
    try:
        for _ in range(30):
            for segment in collect(collector, 20):
                behavior = segment.get_non_tensor(keys.BEHAVIOR)
                obs, memory = segment[keys.OBS, "Echo"].numpy(), segment[keys.MEMORY].numpy()
                for row in range(segment.batch_size[0]):
                    key = (behavior, int(obs[row, 0]))
                    rows.setdefault(key, []).append(
                        (obs[row, 1], obs[row, 2], obs[row], memory[row])
                    )
        actors = dict(collector.actors)
    finally:
        collector.close()
    firsts = chained = gaps = carried = 0
    for (behavior, _), steps in rows.items():
        steps.sort(key=lambda s: (s[0], s[1]))  # episode, then step within it
        for index, (episode, step, _, memory) in enumerate(steps):
            if step == 0:
                np.testing.assert_array_equal(memory, 0.0)
                firsts += 1
                continue
            before = steps[index - 1] if index else None
            if before is None or before[0] != episode:
                continue  # the episode's earlier steps were not collected yet
            after = actors[behavior].act_recurrent(
                {"Echo": before[2][None]}, None, before[3][None]
            )[3]
            # relative: recomputed alone, not in the decision's batch, the matrix products
            # round apart by a few units in the last place (4e-6 at a cell state of -22)
            np.testing.assert_allclose(memory, after[0], rtol=1e-5, atol=1e-6)
            chained += 1
            gaps += step - before[1] > 1  # the agent skipped decisions in between
            carried += bool(np.abs(memory).max() > 0)  # (agent 0's first, all zeros, gives 0)
    assert firsts > 10 and chained > 200 and gaps > 5, (firsts, chained, gaps)
    assert carried > chained - 5
