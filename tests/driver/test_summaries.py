"""What a run reports: each behavior's summaries at its own summary_freq, and Unity's custom
statistics in TensorBoard as mlagents-learn aggregates them."""

from __future__ import annotations

import io

from rich.console import Console
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from driver.training.summaries import Summaries
from learners.host.counters import LearnerStats
from learners.trainer_config.parse import parse_config
from learners.trainer_config.settings import TrainerSettings
from rollout.serving.metrics import ServiceMetrics, Stat, WorkerReports, merge_stats
from rollout.serving.metrics import StatsAggregationMethod as Method  # after rollout's compat


def every_100(behavior: str) -> TrainerSettings:
    return TrainerSettings(summary_freq=100)


def test_summaries_follow_each_behaviors_summary_freq(tmp_path):
    config = parse_config({"behaviors": {"A": {"summary_freq": 100}, "B": {"summary_freq": 250}}})
    written: list[tuple[str, int]] = []
    with Summaries(tmp_path, config.for_behavior, progress=False) as summaries:
        summaries._write = lambda behavior, step, *rest: written.append((behavior, step))
        for step in range(0, 601, 50):
            progress = {
                "steps": {"A?team=0": step, "B?team=0": step},
                "version": 0,
                "stats": LearnerStats(),
            }
            summaries.observe(ServiceMetrics(), progress, [])
    assert [s for b, s in written if b == "A?team=0"] == [100, 200, 300, 400, 500, 600]
    assert [s for b, s in written if b == "B?team=0"] == [250, 500]


def test_a_run_whose_first_look_comes_late_still_writes_its_first_summary(tmp_path):
    """A resumed run at step 1,000 seen first at 1,350 (a fast run, a slow first look) is
    past its first boundary (1,100): that summary is written at once, not skipped."""
    written: list[int] = []
    start = {"A?team=0": 1000}
    with Summaries(tmp_path, every_100, progress=False, start_steps=start) as summaries:
        summaries._write = lambda behavior, step, *rest: written.append(step)
        for step in (1350, 1390, 1420):
            progress = {"steps": {"A?team=0": step}, "version": 0, "stats": LearnerStats()}
            summaries.observe(ServiceMetrics(), progress, [])
    assert written == [1350, 1420]


def test_a_summary_without_finished_episodes_still_prints_its_step(tmp_path):
    """As mlagents-learn: without a TTY every summary prints a line, with the step."""

    out = io.StringIO()
    console = Console(file=out, width=200)
    with Summaries(tmp_path, every_100, progress=False, console=console) as summaries:
        progress = {"steps": {"A?team=0": 150}, "version": 0, "stats": LearnerStats()}
        summaries.observe(ServiceMetrics(), progress, [])
    assert "A. Step: 150. Time Elapsed: " in out.getvalue()  # named as mlagents-learn names it
    assert "No episode was completed since last summary." in out.getvalue()


def test_updates_no_summary_took_are_written_at_the_runs_end(tmp_path):
    """A short run past its last summary before the learner's first update (its steps
    counted while the learner was still starting): the update is written at the end, at
    the final step, and an update a summary already took is not written twice."""
    with Summaries(tmp_path, every_100, progress=False, console=Console(file=io.StringIO())) as s:
        stats = LearnerStats()
        s.observe(ServiceMetrics(), {"steps": {"A?team=0": 120}, "stats": stats}, [])
        taken = [("A?team=0", 120, {"Losses/Q1 Loss": 4.0})]
        s.observe(ServiceMetrics(), {"steps": {"A?team=0": 210}, "stats": stats}, taken)
        late = [
            ("A?team=0", 230, {"Losses/Q1 Loss": 1.0}),
            ("A?team=0", 250, {"Losses/Q1 Loss": 2.0}),
        ]
        s.last_updates(late, {"A?team=0": 260})
        s.last_updates([], {"A?team=0": 260})  # nothing left: nothing written
    scalars = EventAccumulator(str(tmp_path / "A")).Reload().Scalars("Losses/Q1 Loss")
    assert [(e.step, e.value) for e in scalars] == [(210, 4.0), (260, 1.5)]


def test_stats_aggregate_as_mlagents_learn_does():
    stats = WorkerReports()
    for worker in (0, 1):
        stats._take_stats(
            worker,
            {
                "Sum": [(1.0, Method.SUM.value), (2.0, Method.SUM.value)],
                "Mean": [(float(worker), Method.AVERAGE.value)],
                "Latest": [(5.0 + worker, Method.MOST_RECENT.value)],
                "Hist": [(float(worker), Method.HISTOGRAM.value)],
            },
        )
    taken = stats.drain_stats()
    assert {k: v.value for k, v in taken.items()} == {
        "Sum": 6.0,
        "Mean": 0.5,
        "Latest": 5.0,  # worker 0's only
        "Hist": 0.5,
    }
    assert taken["Hist"].values == [0.0, 1.0] and stats.drain_stats() == {}
    window: dict[str, Stat] = {}
    merge_stats(window, taken)
    merge_stats(window, {"Sum": taken["Sum"]})
    assert window["Sum"].value == 12.0 and window["Sum"] is not taken["Sum"]


def test_custom_stats_reach_every_behaviors_tensorboard(tmp_path):
    metrics = ServiceMetrics()
    with Summaries(tmp_path, every_100, progress=False) as summaries:
        for step, goals in ((60, 1.0), (120, 2.0), (180, 4.0), (240, 8.0)):
            merge_stats(metrics.unity_stats, {"Environment/Goals": Stat(Method.SUM)})
            metrics.unity_stats["Environment/Goals"].add(goals)
            metrics.unity_stats.setdefault("Spread", Stat(Method.HISTOGRAM)).add(goals)
            steps = {"Striker?team=0": step, "Goalie?team=1": step}
            summaries.observe(metrics, {"steps": steps, "version": 0, "stats": LearnerStats()}, [])
    for folder in ("Striker", "Goalie"):  # without their teams, as mlagents-learn writes them
        events = EventAccumulator(str(tmp_path / folder), size_guidance={"histograms": 0})
        events.Reload()
        goals = [(e.step, e.value) for e in events.Scalars("Environment/Goals")]
        assert goals == [(120, 3.0), (240, 12.0)]  # summed over each summary period
        assert [h.step for h in events.Histograms("Spread_hist")] == [120, 240]


def test_behaviors_are_named_without_their_team_unless_two_teams_train_apart(tmp_path):
    """mlagents-learn names a trainer, its console lines and its TensorBoard folder after
    the behavior without ``?team=``; two teams trained apart (no self-play) need two."""
    out = io.StringIO()
    console = Console(file=out, width=200)
    steps = {"Soccer?team=1": 100, "Soccer?team=0": 100, "Walker?team=0": 100}
    with Summaries(tmp_path, every_100, progress=False, console=console) as summaries:
        summaries.observe(
            ServiceMetrics(), {"steps": steps, "version": 0, "stats": LearnerStats()}, []
        )
    lines = [line.split(".")[0] for line in out.getvalue().splitlines() if "Step: 100" in line]
    assert lines == ["Soccer", "Soccer?team=0", "Walker"]
    folders = sorted(p.name for p in tmp_path.iterdir() if p.is_dir())
    assert folders == ["Soccer", "Soccer_team0", "Walker"]


def test_the_extrinsic_reward_is_written_per_episode_with_group_rewards_as_mlagents_learn(
    tmp_path,
):
    """``Policy/Extrinsic Reward``: each episode's rewards with its group rewards (POCA's
    with its groupmates' rewards too), times the strength, over the episodes since the last
    summary; not written for a behavior without the extrinsic signal."""
    from rollout.collecting.collector import BehaviorStats, CollectorMetrics

    config = parse_config(
        {
            "behaviors": {
                "Ppo": {"summary_freq": 100, "reward_signals": {"extrinsic": {"strength": 0.5}}},
                "Poca": {"trainer_type": "poca", "summary_freq": 100},
                "Curious": {
                    "summary_freq": 100,
                    "reward_signals": {"curiosity": {"strength": 0.02, "gamma": 0.99}},
                },
            }
        }
    )
    metrics = ServiceMetrics()
    with Summaries(tmp_path, config.for_behavior, progress=False) as summaries:
        for step, episodes in ((100, 2), (200, 6)):  # 4 more episodes in the second summary
            stats = {
                name: BehaviorStats(
                    episodes=episodes,
                    return_sum=1.0 * episodes,
                    episode_group_sum=3.0 * episodes,
                    episode_mates_sum=10.0 * episodes,
                )
                for name in ("Ppo?team=0", "Poca?team=0", "Curious?team=0")
            }
            metrics.workers = [CollectorMetrics(behaviors=stats)]
            steps = dict.fromkeys(stats, step)
            summaries.observe(metrics, {"steps": steps, "version": 0, "stats": LearnerStats()}, [])

    def written(folder: str) -> list[tuple[int, float]]:
        events = EventAccumulator(str(tmp_path / folder)).Reload()
        if "Policy/Extrinsic Reward" not in events.Tags()["scalars"]:
            return []
        return [(e.step, e.value) for e in events.Scalars("Policy/Extrinsic Reward")]

    assert written("Ppo") == [(100, 0.5 * 4.0), (200, 0.5 * 4.0)]  # (1 + 3) per episode
    assert written("Poca") == [(100, 14.0), (200, 14.0)]  # 1 + 3 + 10
    assert written("Curious") == []  # its reward_signals leave the extrinsic one out
