"""Resident memory of every process of a long training run, to show that nothing grows
without bound (issue 29: Unity's custom statistics, metrics, ledgers, summaries).

Starts ``unity-rollout train`` for ``--minutes`` in a session of its own and samples, every
``--every`` seconds, the resident memory of each process under it: the driver, Ray's
own (GCS, raylet, ...), the learner, the rollout workers and their Unity players. Reported
per process (by role and pid): its memory after ``--warmup`` minutes, at the end, and the
slope of a least-squares line over the samples after the warm-up, in MB per hour. The
default run, unitysim Echo with the default PPO settings, is the hard case for anything
kept per agent or per statistic: agents join and leave for good (new ids all run long),
switch behaviors, and the build sends StatsRecorder entries at nearly every step.

    .venv/bin/python -m benchmarks.costs.bench_memory_flat --minutes 60 --json /tmp/memory.json

Every process the run started is ended with its session (by process group) when it ends.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

from benchmarks.common import ROOT, machine

ROLES = (  # the first marker found in a process's command line names its role
    ("-m driver.cli", "driver"),
    ("ray::RolloutWorker", "worker"),
    ("ray::RayLearner", "learner"),
    ("unitysim play", "player"),
    ("gcs_server", "ray gcs"),
    ("raylet", "ray raylet"),
)


def role(process: psutil.Process) -> str:
    try:
        line = " ".join(process.cmdline())
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return "gone"
    return next((name for marker, name in ROLES if marker in line), "ray other")


def sample(root: psutil.Process) -> dict[str, float]:
    """``role:pid`` -> resident MB, for the run's process and everything under it."""
    found = {}
    try:
        processes = [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return found
    for process in processes:
        try:
            found[f"{role(process)}:{process.pid}"] = process.memory_info().rss / 2**20
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return found


def slope_per_hour(times: list[float], values: list[float]) -> float:
    if len(times) < 3:
        return float("nan")
    return float(np.polyfit(np.asarray(times) / 3600.0, np.asarray(values), 1)[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="unitysim:Echo")
    parser.add_argument("--config", help="a trainer config (default: the env's in config/)")
    parser.add_argument("--minutes", type=float, default=60.0)
    parser.add_argument("--warmup", type=float, default=10.0, help="minutes before the fit")
    parser.add_argument("--every", type=float, default=30.0, help="seconds between samples")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", help="write the results here too")
    args = parser.parse_args()

    results = Path(tempfile.mkdtemp(prefix="bench-memory-"))
    command = [
        sys.executable, "-m", "driver.cli", "train", "--env", args.env, "--no-progress",
        "--workers", str(args.workers), "--max-seconds", str(args.minutes * 60),
        "--max-steps", "1000000000", "--results-dir", str(results), "--run-id", "memory",
    ]  # fmt: skip
    if args.config:
        command += ["--config", args.config]
    log = (results / "train.log").open("w")
    process = subprocess.Popen(
        command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
    )
    root = psutil.Process(process.pid)
    started = time.monotonic()
    series: dict[str, list[tuple[float, float]]] = {}
    try:
        while process.poll() is None:
            now = time.monotonic() - started
            for key, mb in sample(root).items():
                series.setdefault(key, []).append((now, mb))
            time.sleep(args.every)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGTERM)
            process.wait(timeout=120)
        with contextlib.suppress(ProcessLookupError):  # what the run left in its session
            os.killpg(process.pid, signal.SIGKILL)
        log.close()

    warmup = args.warmup * 60
    rows = []
    for key, points in sorted(series.items()):
        after = [(t, mb) for t, mb in points if t >= warmup]
        if len(after) < 3:
            continue  # a short-lived helper, gone before the warm-up ended
        times, values = zip(*after, strict=True)
        rows.append({
            "process": key,
            "at_warmup_mb": round(values[0], 1),
            "at_end_mb": round(values[-1], 1),
            "slope_mb_per_hour": round(slope_per_hour(list(times), list(values)), 1),
            "samples": len(after),
        })  # fmt: skip
    report = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "command": " ".join(command[1:]),
        "minutes": args.minutes,
        "exit_code": process.returncode,
        "summary": json.loads((results / "memory" / "summary.json").read_text())
        if (results / "memory" / "summary.json").is_file()
        else None,
        "processes": rows,
    }
    print(f"{'process':28} {'after warm-up':>14} {'at end':>10} {'MB/hour':>9}")
    for row in rows:
        print(
            f"{row['process']:28} {row['at_warmup_mb']:14.1f} {row['at_end_mb']:10.1f} "
            f"{row['slope_mb_per_hour']:9.1f}"
        )
    print(f"exit code {process.returncode}; run directory {results}")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
