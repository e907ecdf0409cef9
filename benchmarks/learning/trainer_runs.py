"""What the learning benchmarks share: a trainer's command run to a level (its summary
lines, mlagents-learn's format, which ``unity-rollout train`` prints too, read live; the
run stopped at the level or a cap; every process it started found by an environment tag
and ended), the unitysim build both trainers run, ML-Agents' configs (with a
recording of unitysim's expert as their ``demo_path``), and a run's TensorBoard scalars."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import psutil
import yaml

from benchmarks.common import ROOT, mlagents_config

SUMMARY = re.compile(
    r"(\S+)\. Step: (\d+)\. Time Elapsed: [\d.]+ s\. Mean Reward: (-?\d+(?:\.\d+)?)"
)
MEASURES = {  # what a summary line adds, as both trainers print it
    "group": re.compile(r"Mean Group Reward: (-?\d+(?:\.\d+)?)"),  # POCA
    "elo": re.compile(r"ELO: (-?\d+(?:\.\d+)?)"),  # self-play
}
MARK = re.compile(r"\[mlbench-mark\] reset_env_done ([\d.]+)")
TAG = "UNITY_ROLLOUT_BENCH_RUN"
# the anchor recipe's work directory (its venv/, shim/ and mlagents_learn_launcher.py)
ANCHOR_DIR = Path(os.environ.get("MLAGENTS_ANCHOR", "/tmp/mlbench"))


@dataclass
class Run:
    variant: str
    seed: int
    summaries: list[tuple[float, int, float]] = field(default_factory=list)  # (s, step, reward)
    first_step_s: float | None = None
    launched_at: float = 0.0  # wall clock of the launch; every figure counts from it
    exit_code: int | None = None
    wall_s: float = 0.0
    leftovers: int = 0
    log: Path | None = None
    first_brain: str | None = None  # the first summary's: self-play's first learning team
    # summaries a level must hold for, on average: 1 reads the first summary at it; more
    # skip an early summary of the few short episodes (Hallway's first goals)
    held: int = 1

    def reached(self, level: float) -> tuple[float, int] | None:
        """(seconds, step) of the first summary from which the mean of ``held``
        summaries is at or above ``level``."""
        rewards = [r for _, _, r in self.summaries]
        for i, (t, s, _) in enumerate(self.summaries[: len(rewards) - self.held + 1]):
            if sum(rewards[i : i + self.held]) / self.held >= level:
                return t, s
        return None

    def end_level(self) -> float | None:
        """The level the run ended at: the mean of its last ``held`` summaries."""
        last = [r for _, _, r in self.summaries[-self.held :]]
        return sum(last) / len(last) if last else None

    def report(self, targets: tuple[float | None, ...]) -> dict:
        levels = {}
        for level in targets:
            if level is None:
                continue
            hit = self.reached(level)
            levels[str(level)] = None if hit is None else {"s": round(hit[0], 1), "step": hit[1]}
        return {
            "variant": self.variant,
            "seed": self.seed,
            "targets": levels,
            "first_step_s": self.first_step_s,
            "first_summary_s": round(self.summaries[0][0], 1) if self.summaries else None,
            "first_brain": self.first_brain,
            "best_reward": max((r for _, _, r in self.summaries), default=None),
            "exit_code": self.exit_code,
            "wall_s": round(self.wall_s, 1),
            "leftover_processes": self.leftovers,
        }


def anchor_command(
    prefix: list[str], config: Path, build: Path, run_id: str, results: Path, port: int, seed: int
) -> list[str]:
    """mlagents-learn as the benchmarks run it (``prefix``: the anchor's Python and launcher):
    2 Unity instances of ``build``, no graphics."""
    return [
        *prefix,
        str(config),
        f"--env={build.with_suffix('')}",
        f"--run-id={run_id}",
        "--no-graphics",
        "--num-envs=2",
        "--force",
        "--results-dir",
        str(results),
        "--base-port",
        str(port),
        "--seed",
        str(seed),
    ]


def our_command(
    prefix: list[str], config: Path, build: Path, run_id: str, results: Path, seed: int,
    seconds: float,
) -> list[str]:  # fmt: skip
    """``unity-rollout train`` as the benchmarks run it (``prefix``: up to ``train``): 2
    workers, as mlagents-learn's 2 instances, stopped after ``seconds`` at the latest; one
    learner thread, as every run beside mlagents-learn was measured before the default
    took every core (on 2 cores beside it, 2 threads slowed ours' SoccerTwos updates from
    about 100 s to 155; a later ``--learner-threads`` in the command overrides it)."""
    return [
        *prefix,
        "--env",
        str(build),
        "--config",
        str(config),
        "--results-dir",
        str(results),
        "--run-id",
        run_id,
        "--seed",
        str(seed),
        "--workers",
        "2",
        "--force",
        "--no-progress",
        "--max-seconds",
        str(seconds),
        "--learner-threads",
        "1",
    ]


def tagged(tag: str) -> list[psutil.Process]:
    found = []
    for process in psutil.process_iter():
        try:
            if process.environ().get(TAG) == tag:
                found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, ProcessLookupError):
            continue
    return found


_LIVE: dict[int, str] = {}  # process group -> tag, of every run in progress


def stop_runs_on_sigterm() -> None:
    """Make a SIGTERM to the benchmark stop the runs it started, then exit: each run is in a
    session of its own, so nothing else stops them (an mlagents-learn run in a thread went on
    alone, holding its ports). Call from the main thread."""

    def stop(signum: int, _frame: object) -> None:
        for group, tag in list(_LIVE.items()):
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(group, signal.SIGKILL)
            for leftover in tagged(tag):
                with contextlib.suppress(psutil.NoSuchProcess):
                    leftover.kill()
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)


def run_command(
    command: list[str],
    env: dict[str, str],
    run: Run,
    stop_signal: signal.Signals,
    log: Path,
    stop_at: float | None,
    cap_s: float,
    measure: str = "reward",
    behavior: str | None = None,
    stop_step: int | None = None,
    cwd: Path | None = None,
) -> None:
    """Run until ``stop_at`` is reached (None: to ``cap_s``) or a summary at ``stop_step``
    steps, reading summary lines live: ``measure`` (the mean reward, or one of
    ``MEASURES``) of ``behavior`` (None: any)."""
    tag = uuid.uuid4().hex
    run.log = log
    started = run.launched_at = time.time()
    process = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        env={**os.environ, **env, TAG: tag, "PYTHONUNBUFFERED": "1"},
        cwd=cwd,
    )
    _LIVE[process.pid] = tag
    done = threading.Event()

    def read() -> None:
        assert process.stdout is not None
        with log.open("w", buffering=1) as out:  # lines: watchable
            for line in process.stdout:
                now = time.time() - started
                out.write(f"[+{now:8.3f}s] {line}")
                if (mark := MARK.search(line)) and run.first_step_s is None:
                    run.first_step_s = round(float(mark.group(1)) - started, 2)
                if match := SUMMARY.search(line):
                    run.first_brain = run.first_brain or match.group(1)
                    if behavior is not None and match.group(1) != behavior:
                        continue
                    reward = float(match.group(3))
                    if measure in MEASURES:
                        value = MEASURES[measure].search(line)
                        if value is None:
                            continue
                        reward = float(value.group(1))
                    run.summaries.append((now, int(match.group(2)), reward))
                    if stop_at is not None and run.reached(stop_at) is not None:
                        done.set()
                    if stop_step is not None and int(match.group(2)) >= stop_step:
                        done.set()
        done.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        done.wait(cap_s)
    finally:  # also on Ctrl-C: the run is in its own session, so stop it here
        if process.poll() is None:
            os.killpg(process.pid, stop_signal)  # graceful: the trainer stops its players
            try:
                process.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
        reader.join(10)
        run.exit_code, run.wall_s = process.returncode, time.time() - started
        left = tagged(tag)
        run.leftovers = len(left)
        for leftover in left:
            leftover.kill()
        _LIVE.pop(process.pid, None)


def build_player(env: str, work: Path) -> Path:
    """unitysim's ``env`` built as a player in ``work``: its executable."""
    subprocess.run(
        [str(ROOT / ".venv/bin/unity-rollout"), "unitysim", "build", str(work / env), "--env", env],
        check=True,
        capture_output=True,
    )
    return work / env / f"{env}.x86_64"


def with_demo(name: str, env: str, demo_steps: int, work: Path) -> Path:
    """ML-Agents' config ``name``; with ``demo_steps``, a copy in ``work`` whose every
    ``demo_path`` names a recording of unitysim's expert on ``env`` (made once)."""
    config = mlagents_config(name)
    if not demo_steps:
        return config
    demo = work / f"{env}-expert.demo"
    if not demo.is_file():
        subprocess.run(
            [
                str(ROOT / ".venv/bin/unity-rollout"),
                "record-demo",
                "--env",
                f"unitysim:{env}",
                "--heuristic",
                "--steps",
                str(demo_steps),
                "--out",
                str(demo),
            ],
            check=True,
            capture_output=True,
        )
    data = yaml.safe_load(config.read_text())
    for settings in data["behaviors"].values():
        for section in (
            settings.get("reward_signals", {}).get("gail"),
            settings.get("behavioral_cloning"),
        ):
            if section is not None:
                section["demo_path"] = str(demo)
    copy = work / name.replace("/", "_")
    copy.write_text(yaml.safe_dump(data))
    return copy


def scalars(run_dir: Path, tag: str, behavior: str | None = None) -> list[tuple[float, int, float]]:
    """(wall time, step, value) of ``tag`` across the run's behaviors (or ``behavior``'s)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    points: list[tuple[float, int, float]] = []
    for behavior_dir in sorted(p for p in run_dir.iterdir() if p.is_dir()):
        if behavior is not None and behavior_dir.name.split("?")[0] != behavior:
            continue
        if not list(behavior_dir.glob("events.out.tfevents.*")):
            continue
        accumulator = EventAccumulator(str(behavior_dir), size_guidance={"scalars": 0}).Reload()
        if tag in accumulator.Tags()["scalars"]:
            points += [(e.wall_time, e.step, e.value) for e in accumulator.Scalars(tag)]
    return sorted(points)
