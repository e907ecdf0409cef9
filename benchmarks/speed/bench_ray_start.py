"""Local Ray's start, side by side: Ray's full head against local mode's lean one.

Each run is a fresh Python process (a warm interpreter would hide the imports): it
starts Ray, then three actors, and reports the seconds of ``ray.init``, of the actors'
first answers, and the CPU seconds Ray's processes used by then. The two kinds run
interleaved, ``--rounds`` pairs. Both call ``driver.local_ray.init_local_ray`` (the
same options); ``plain`` with its ``_lean_head`` replaced by a no-op, so Ray starts its
full head, ``lean`` as local mode runs it.

    .venv/bin/python -m benchmarks.speed.bench_ray_start --rounds 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from benchmarks.common import ROOT, machine

ONE_RUN = """
import contextlib, json, os, sys, time
import psutil, ray
from driver import local_ray
if sys.argv[1] == "plain":
    local_ray._lean_head = contextlib.nullcontext
begin = time.perf_counter()
local_ray.init_local_ray(2)
up = time.perf_counter()

@ray.remote(num_cpus=0)
class Probe:
    def pid(self):
        return os.getpid()

probes = [Probe.remote() for _ in range(3)]
ray.get([p.pid.remote() for p in probes])
ready = time.perf_counter()
cpu = 0.0
children = psutil.Process().children(recursive=True)
for child in children:
    try:
        times = child.cpu_times()
        cpu += times.user + times.system
    except psutil.Error:
        pass
processes = sorted(ray._private.worker._global_node.all_processes)
ray.shutdown()
print(json.dumps({"init_s": up - begin, "actors_s": ready - up, "ray_cpu_s": cpu,
                  "processes": processes}))
"""


def one(kind: str) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", ONE_RUN, kind],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    runs: dict[str, list[dict]] = {"plain": [], "lean": []}
    for round_ in range(args.rounds):
        for kind in runs:
            result = one(kind)
            runs[kind].append(result)
            print(
                f"round {round_} {kind:<5} ray.init {result['init_s']:.2f} s, "
                f"3 actors {result['actors_s']:.2f} s, Ray's CPU {result['ray_cpu_s']:.2f} s "
                f"({', '.join(result['processes'])})",
                flush=True,
            )
    ratios = [
        lean["init_s"] / plain["init_s"]
        for plain, lean in zip(runs["plain"], runs["lean"], strict=True)
    ]
    report = {
        "machine": machine(),
        "runs": runs,
        "init_ratio_lean_to_plain": {
            "median": statistics.median(ratios),
            "min": min(ratios),
            "max": max(ratios),
        },
    }
    print(json.dumps(report["init_ratio_lean_to_plain"]))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
