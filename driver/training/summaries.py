"""What a training run reports: TensorBoard event files with ML-Agents' tag names, and a
live rich display. Driver-side only; it reads the service's metrics and the learner's
update reports and never touches segment data.

Tags (docs/training.md lists them all): ``Environment/Cumulative Reward`` and
``Environment/Episode Length`` (episodes finished since the last summary),
``Environment/Lesson Number/<parameter>`` (each curriculum's lesson),
``Losses/*`` and ``Policy/*`` (means over the updates since the last summary; at the
run's end, those of the updates no summary took, at the final step),
``Health/*`` (Unity restarts, dropped steps, policy lag), ``Perf/*`` (agent steps per
second collected, samples per second consumed by the learner), and Unity's custom
statistics (``StatsRecorder``) under their own names in every behavior's folder, as
mlagents-learn writes them (``rollout.serving.metrics.Stat``; histograms also as
``<name>_hist``). One writer per behavior, in ``<run dir>/<name>/``, and summary lines
``<name>. Step: ...``, named as mlagents-learn names its trainers: the behavior without
its team (``3DBall``, a self-play brain ``SoccerTwos``), so TensorBoard shows one run per
behavior under the same names. Without the live display (``--no-progress``, or output
that is not a terminal) each summary is also one line on the console, in mlagents-learn's
words.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.live import Live
from rich.table import Table
from tensorboard.compat.proto.event_pb2 import Event
from tensorboard.compat.proto.summary_pb2 import HistogramProto, Summary
from tensorboard.summary.writer.event_file_writer import EventFileWriter

from batches.contracts import base_name
from learners.trainer_config.settings import TrainerSettings
from rollout.serving.metrics import ServiceMetrics, Stat, merge_stats

_RATE_TAGS = {
    "collect": "Perf/Agent Steps per Second",
    "learn": "Perf/Learner Samples per Second",
    "capacity": "Perf/Learner Samples per Busy Second",
    "busy": "Perf/Learner Busy Fraction",
}


class ScalarWriter:
    """TensorBoard scalars into ``events.out.tfevents.*`` files, as torch's SummaryWriter
    writes them (it uses the same EventFileWriter), without loading torch in the driver."""

    def __init__(self, log_dir: str) -> None:
        self._events = EventFileWriter(log_dir)

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        summary = Summary(value=[Summary.Value(tag=tag, simple_value=float(value))])
        self._events.add_event(Event(wall_time=time.time(), step=int(step), summary=summary))

    def add_histogram(self, tag: str, values: Sequence[float], step: int, bins: int = 30) -> None:
        data = np.asarray(values, dtype=np.float64)
        counts, edges = np.histogram(data, bins=bins)
        histogram = HistogramProto(
            min=float(data.min()),
            max=float(data.max()),
            num=float(data.size),
            sum=float(data.sum()),
            sum_squares=float(np.square(data).sum()),
            bucket_limit=edges[1:].tolist(),
            bucket=counts.astype(np.float64).tolist(),
        )
        summary = Summary(value=[Summary.Value(tag=tag, histo=histogram)])
        self._events.add_event(Event(wall_time=time.time(), step=int(step), summary=summary))

    def flush(self) -> None:
        self._events.flush()

    def close(self) -> None:
        self._events.close()


def next_multiple(step: int, every: int) -> int:
    """The first multiple of ``every`` after ``step``: when a periodic action is due next."""
    every = max(every, 1)
    return (step // every + 1) * every


@dataclass
class _Window:
    """Per behavior: totals at the last summary and update metrics since."""

    next_step: int = 0
    episodes: int = 0
    return_sum: float = 0.0
    length_sum: int = 0
    group_episodes: int = 0
    group_return_sum: float = 0.0
    extras: tuple[float, float] = (0.0, 0.0)  # ServiceMetrics.episode_extras at the last one
    losses: dict[str, list[float]] = field(default_factory=dict)
    unity_stats: dict[str, Stat] = field(default_factory=dict)  # since the last summary
    last_reward: float | None = None
    last_length: float | None = None


class Summaries:
    def __init__(
        self,
        run_dir: Path,
        settings: Callable[[str], TrainerSettings],
        progress: bool = True,
        console: Console | None = None,
        start_steps: Mapping[str, int] | None = None,
    ) -> None:
        self.run_dir = run_dir
        self.settings = settings  # each behavior's (summary_freq, the extrinsic signal)
        # per behavior, the step the run starts from (a resumed run's checkpoint): the first
        # summary is due at the first multiple of summary_freq after it, however late the
        # first look at the learner comes (a short or fast run may be past it by then)
        self.start_steps = dict(start_steps or {})
        self.writers: dict[str, ScalarWriter] = {}
        self.names: dict[str, str] = {}  # behavior -> its name on the console and in TensorBoard
        self.windows: dict[str, _Window] = {}
        self.console = console or Console()
        self.live = Live(console=self.console, auto_refresh=False) if progress else None
        self.started = time.perf_counter()
        self.rates: dict[str, float] = {}
        self.first_reward_at: float | None = None  # wall clock of the first mean reward
        self._last_rate = (self.started, 0, 0, 0.0)
        self._faults = ServiceMetrics().faults()  # printed when they change (no live table)
        self.lessons: Mapping[str, int] = {}  # environment parameter -> its lesson number

    def __enter__(self) -> Summaries:
        if self.live is not None:
            self.live.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self.live is not None:
            self.live.stop()
        for writer in self.writers.values():
            writer.close()

    def observe(
        self,
        metrics: ServiceMetrics,
        progress: dict[str, Any],
        reports: list[tuple[str, int, dict[str, float]]],
    ) -> None:
        """Fold in the newest numbers; write a summary for each behavior past its period."""
        now = time.perf_counter()
        stats = progress["stats"]
        then, steps_then, samples_then, busy_then = self._last_rate
        total = sum(progress["steps"].values())
        if now - then >= 2.0:
            busy = stats.update_seconds - busy_then
            self.rates = {
                "collect": (total - steps_then) / (now - then),
                "learn": (stats.samples - samples_then) / (now - then),
                # what the learner could take if never idle, and how often it is busy
                "capacity": (stats.samples - samples_then) / busy if busy > 0 else 0.0,
                "busy": busy / (now - then),
            }
            self._last_rate = (now, total, stats.samples, stats.update_seconds)
        self._fold(reports, progress["steps"])
        unity_stats = metrics.drain_unity_stats()
        totals = metrics.episode_totals()
        for behavior, step in progress["steps"].items():
            window = self._window(behavior, step)
            merge_stats(window.unity_stats, unity_stats)
            if step >= window.next_step:
                self._write(behavior, step, window, totals.get(behavior), metrics)
                window.next_step = next_multiple(step, self.settings(behavior).summary_freq)
        if self.live is not None:
            self.live.update(self._table(metrics, progress), refresh=True)
        elif (faults := metrics.faults()) != self._faults:  # a line per change, as it happens
            self.console.print(f"faults: {_faults_text(faults)}", soft_wrap=True, highlight=False)
            self._faults = faults

    def last_updates(
        self, reports: list[tuple[str, int, dict[str, float]]], steps: Mapping[str, int]
    ) -> None:
        """At the run's end: the update metrics no summary took (updates after the last
        one, or a short run's updates that all came after it), written at each behavior's
        final step, so that TensorBoard has every update."""
        self._fold(reports, steps)
        for behavior, window in self.windows.items():
            if window.losses:
                writer = self._writer(behavior)
                self._write_updates(writer, window, steps.get(behavior, 0))
                writer.flush()

    def _fold(
        self, reports: list[tuple[str, int, dict[str, float]]], steps: Mapping[str, int]
    ) -> None:
        """Each update's metrics into its behavior's window, until a summary writes them."""
        for behavior, _, report in reports:
            window = self._window(behavior, steps.get(behavior, 0))
            for key, value in report.items():
                window.losses.setdefault(key, []).append(value)

    @staticmethod
    def _write_updates(writer: ScalarWriter, window: _Window, step: int) -> None:
        """The means of the window's update metrics at ``step``; the window starts anew."""
        for key, values in window.losses.items():
            writer.add_scalar(key, sum(values) / len(values), step)
        window.losses = {}

    def name(self, behavior: str) -> str:
        """The behavior without its team, as mlagents-learn names a trainer; a second
        behavior of that name (its teams trained apart) keeps its team."""
        if behavior not in self.names:
            base = base_name(behavior)
            self.names[behavior] = behavior if base in self.names.values() else base
        return self.names[behavior]

    def _window(self, behavior: str, step: int) -> _Window:
        if behavior not in self.windows:
            start = min(step, self.start_steps.get(behavior, 0))
            self.windows[behavior] = _Window(
                next_step=next_multiple(start, self.settings(behavior).summary_freq)
            )
        return self.windows[behavior]

    def _writer(self, behavior: str) -> ScalarWriter:
        if behavior not in self.writers:
            folder = self.run_dir / behavior_folder(self.name(behavior))
            self.writers[behavior] = ScalarWriter(str(folder))
        return self.writers[behavior]

    def _write(
        self,
        behavior: str,
        step: int,
        window: _Window,
        totals: tuple[int, float, int] | None,
        metrics: ServiceMetrics,
    ) -> None:
        writer = self._writer(behavior)
        episodes, return_sum, length_sum = totals or (window.episodes, 0.0, 0)
        new = episodes - window.episodes
        line = "No episode was completed since last summary."  # mlagents-learn's words
        if new > 0:
            window.last_reward = (return_sum - window.return_sum) / new
            window.last_length = (length_sum - window.length_sum) / new
            writer.add_scalar("Environment/Cumulative Reward", window.last_reward, step)
            writer.add_scalar("Environment/Episode Length", window.last_length, step)
            writer.add_scalar("Environment/Episodes", new, step)
            self.first_reward_at = self.first_reward_at or time.time()
            line = (
                f"Mean Reward: {window.last_reward:.3f}. Episode Length: {window.last_length:.1f}."
            )
            extras = metrics.episode_extras().get(behavior, window.extras)
            gained = (return_sum - window.return_sum, new)
            self._extrinsic_reward(writer, behavior, step, gained, extras)
            window.extras = extras
            line += self._group_reward(writer, behavior, step, window, metrics)
            if elo := window.losses.get("Self-play/ELO"):  # as mlagents-learn's line
                line += f" ELO: {elo[-1]:.3f}."
        if self.live is None:
            elapsed = time.perf_counter() - self.started
            self.console.print(
                f"{self.name(behavior)}. Step: {step}. Time Elapsed: {elapsed:.1f} s. {line}",
                soft_wrap=True,
                highlight=False,
            )
        if totals is not None:
            window.episodes, window.return_sum, window.length_sum = totals
        self._write_updates(writer, window, step)
        for key, stat in window.unity_stats.items():
            writer.add_scalar(key, stat.value, step)
            if stat.values:
                writer.add_histogram(f"{key}_hist", stat.values, step)
        window.unity_stats = {}
        for name, number in self.lessons.items():
            writer.add_scalar(f"Environment/Lesson Number/{name}", number, step)
        writer.add_scalar("Health/Unity Restarts", metrics.unity_restarts, step)
        writer.add_scalar("Health/Worker Restarts", metrics.worker_restarts, step)
        writer.add_scalar("Health/Learner Restarts", metrics.learner_restarts, step)
        writer.add_scalar("Health/Dropped Steps", metrics.faults()["dropped_steps"], step)
        writer.add_scalar("Health/Policy Lag", metrics.policy_lag_mean, step)
        for name, rate in self.rates.items():
            writer.add_scalar(_RATE_TAGS[name], rate, step)
        writer.flush()

    def _extrinsic_reward(
        self,
        writer: ScalarWriter,
        behavior: str,
        step: int,
        gained: tuple[float, int],
        extras: tuple[float, float],
    ) -> None:
        """ML-Agents' ``Policy/Extrinsic Reward``: over the episodes since the last summary,
        the mean of each one's rewards with its group rewards (under POCA with its
        groupmates' rewards too), times the signal's strength; none without the signal.
        ``extras``: the group and groupmates' rewards within all episodes so far."""
        settings, window = self.settings(behavior), self.windows[behavior]
        if not settings.reward_strength:
            return
        returns, episodes = gained
        group, mates = extras
        total = returns + group - window.extras[0]
        if settings.trainer_type == "poca":
            total += mates - window.extras[1]
        writer.add_scalar(
            "Policy/Extrinsic Reward", settings.reward_strength * total / episodes, step
        )

    @staticmethod
    def _group_reward(
        writer: ScalarWriter, behavior: str, step: int, window: _Window, metrics: ServiceMetrics
    ) -> str:
        """ML-Agents' mean group reward of the episodes that ended with their group since
        the last summary ("" for a behavior without groups)."""
        episodes, rewards = metrics.group_totals().get(behavior, (0, 0.0))
        new, gained = episodes - window.group_episodes, rewards - window.group_return_sum
        window.group_episodes, window.group_return_sum = episodes, rewards
        if new <= 0:
            return ""
        mean = gained / new
        writer.add_scalar("Environment/Group Cumulative Reward", mean, step)
        return f" Mean Group Reward: {mean:.3f}."

    def _table(self, metrics: ServiceMetrics, progress: dict[str, Any]) -> Table:
        elapsed = time.perf_counter() - self.started
        table = Table(
            title=(
                f"unity-rollout  {elapsed:6.0f}s  "
                f"{self.rates.get('collect', 0):,.0f} steps/s  "
                f"learner {self.rates.get('learn', 0):,.0f} samples/s  "
                f"lag {metrics.policy_lag_mean:.2f}\nfaults: {_faults_text(metrics.faults())}"
                + "".join(f"\nlesson {n} of {name}" for name, n in self.lessons.items())
            ),
            title_justify="left",
        )
        for column in ("behavior", "step", "mean reward", "episode length", "policy version"):
            table.add_column(column, justify="right" if column != "behavior" else "left")
        for behavior, step in sorted(progress["steps"].items()):
            window = self.windows.get(behavior, _Window())
            table.add_row(
                behavior,
                f"{step:,}",
                "-" if window.last_reward is None else f"{window.last_reward:.3f}",
                "-" if window.last_length is None else f"{window.last_length:.1f}",
                str(progress["version"]),
            )
        return table

    def latest(self) -> dict[str, dict[str, float | None]]:
        """Per behavior, the mean reward and episode length of the last summary."""
        return {
            name: {"mean_reward": w.last_reward, "episode_length": w.last_length}
            for name, w in self.windows.items()
        }


def _faults_text(faults: dict[str, int]) -> str:
    return (
        f"unity restarts {faults['unity_restarts']}, worker restarts "
        f"{faults['worker_restarts']}, learner restarts {faults['learner_restarts']}, "
        f"steps dropped {faults['dropped_steps']:,}"
    )


def behavior_folder(behavior: str) -> str:
    """A behavior's folder name in the run directory (``3DBall?team=0`` -> ``3DBall_team0``)."""
    return behavior.replace("?", "_").replace("=", "")
