"""Learning at fixed steps, and the size of each update, against mlagents-learn: an
ML-Agents config under both trainers on the same unitysim build, every run to the same
step budget, side by side.

Per seed, mlagents-learn runs while ours run one after the other beside it (not pinned to
cores): this tree; with ``--base-tree DIR`` also the code in DIR (a checkout of another
commit); with ``--also-config NAME`` this tree on a second config too (the config without
its memory, say: the feature's effect in the same run). Each run is stopped at its first
summary at or past ``--steps``. The report gives, per run and in the median over seeds:
the mean reward of the summary nearest each of ``--marks``, the first summary at or
above each of ``--levels``, and the mean number of steps an update trained on, per
stretch between marks (mlagents-learn's from the steps at which each update began, as
``mlagents_update_log.py`` writes them down; ours' from ``Policy/Samples``).

    .venv/bin/python -m benchmarks.learning.bench_fixed_steps --config ppo/Pyramids.yaml \\
        --env Pyramids --seeds 10 11 12 --steps 540000 [--base-tree /tmp/base] [--json F]

``--measure group`` reads POCA's mean group reward (DungeonEscape), ``elo`` self-play's ELO
(``--behavior Striker``: one behavior's, where a game has two; ``--anchor-first-brain
Striker`` gives mlagents-learn's first turn to the team ours gives it to, which its hash
seed otherwise picks). ``--ours-option
--mixed-precision`` (repeatable) adds an option to ours' command line.
An imitation config (``imitation/Pyramids.yaml``) takes ``--demo-steps 5000``: both
trainers then read one recording of unitysim's scripted expert as its ``demo_path``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

from batches.contracts import base_name
from benchmarks.common import ROOT, machine
from benchmarks.learning.trainer_runs import (
    ANCHOR_DIR,
    MEASURES,
    Run,
    anchor_command,
    build_player,
    our_command,
    run_command,
    scalars,
    stop_runs_on_sigterm,
    with_demo,
)
from unitysim.envs import load

# run by the anchor's own Python, as a file (it imports nothing of ours)
UPDATE_LOG = ROOT / "benchmarks" / "equality" / "mlagents_update_log.py"
Side = tuple[str, Path, Path]  # run name, source tree, config


def anchor_run(args: argparse.Namespace, seed: int, build: Path, work: Path) -> dict[str, Any]:
    updates = work / f"ml-{seed}.updates.jsonl"
    prefix = [str(args.anchor / "venv/bin/python"), str(UPDATE_LOG)]
    prefix.append(str(args.anchor / "mlagents_learn_launcher.py"))
    command = anchor_command(
        prefix, args.config_path, build, f"ml-{seed}", work / "mlagents", 31000 + 10 * seed,
        seed,
    )  # fmt: skip
    env = {"PYTHONPATH": str(args.anchor / "shim"), "UPDATE_LOG": str(updates)}
    if args.anchor_hash_seed is not None:
        env["PYTHONHASHSEED"] = str(args.anchor_hash_seed)
    run = Run("mlagents-learn", seed)
    run_command(
        command, env, run, signal.SIGTERM, work / f"ml-{seed}.log", None, args.cap,
        args.measure, args.behavior, stop_step=args.steps,
    )  # fmt: skip
    lines = updates.read_text().splitlines() if updates.is_file() else []  # none: it failed
    updates = [json.loads(line) for line in lines]  # [step, buffered, brain]
    mine = [u[0] for u in updates if args.behavior in (None, *u[2:])]  # one brain's own
    return report(run, steps_between(mine), args)


def hash_seed_putting_first(args: argparse.Namespace, brain: str) -> int:
    """A PYTHONHASHSEED under which mlagents-learn registers ``brain`` first.

    It registers a build's behaviors in the order of a set of their names
    (``TrainerController._register_new_behaviors``), and its ghost controller gives the
    first team registered the first turn; unpinned, that order changes with each process's
    hash seed. Ours gives it to the build's first behavior."""
    names = [b.name for b in load(args.env).behaviors]
    probe = "import sys; s = set(); s |= set(sys.argv[1:]); print(next(iter(s - set())))"
    python = str(args.anchor / "venv/bin/python")
    for seed in range(256):
        env = {**os.environ, "PYTHONHASHSEED": str(seed)}
        first = subprocess.run(
            [python, "-c", probe, *names], env=env, capture_output=True, text=True, check=True
        ).stdout.strip()
        if base_name(first) == brain:
            return seed
    raise SystemExit(f"--anchor-first-brain: no hash seed puts {brain} first among {names}")


def steps_between(at: list[int]) -> list[tuple[int, int]]:
    """(step, size) per update of mlagents-learn, from the steps at which each began: the
    agent steps it trained on. Its buffer's own count would add a recurrent policy's
    padding to whole sequences, which trains nothing."""
    return [(step, step - before) for before, step in zip([0, *at], at, strict=False)]


def our_run(
    args: argparse.Namespace, seed: int, build: Path, work: Path, side: Side
) -> dict[str, Any]:
    name, tree, config = side
    run_id = f"{name}-{seed}"
    prefix = [sys.executable, "-m", "driver.cli", "train"]
    results = work / "ours"
    command = our_command(prefix, config, build, run_id, results, seed, args.cap)
    command += args.ours_option
    run = Run(name, seed)
    run_command(
        command, {"PYTHONPATH": str(tree)}, run, signal.SIGINT, work / f"{run_id}.log", None,
        args.cap + 60, args.measure, args.behavior, stop_step=args.steps, cwd=tree,
    )  # fmt: skip
    samples = scalars(work / "ours" / run_id, "Policy/Samples", args.behavior)
    return report(run, update_sizes(samples), args)


def update_sizes(samples: list[tuple[float, int, float]]) -> list[tuple[int, int]]:
    """(step, size) per update, from each summary's mean size: its steps in updates of it,
    dated at the summary (one behavior's run)."""
    out, last = [], 0
    for _, step, mean in samples:
        if mean <= 0:
            continue
        count = max(round((step - last) / mean), 1)
        out += [(step, round(mean))] * count
        last = step
    return out


def report(run: Run, sizes: list[tuple[int, int]], args: argparse.Namespace) -> dict[str, Any]:
    near = {}
    for mark in args.marks:
        if run.summaries and run.summaries[-1][1] >= mark - args.spacing:
            near[mark] = min(run.summaries, key=lambda s: abs(s[1] - mark))[2]
    first, seconds = {}, {}
    for level in args.levels:
        hit = run.reached(level)
        first[level] = None if hit is None else hit[1]
        seconds[level] = None if hit is None else round(hit[0], 1)
    stretches, start = {}, 0
    for mark in [*args.marks, args.steps]:  # the last takes the summary past --steps too
        end = mark if mark != args.steps else float("inf")
        inside = [size for step, size in sizes if start < step <= end]
        if inside:
            stretches[f"{start // 1000}k-{mark // 1000}k"] = round(statistics.mean(inside))
        start = mark
    return {
        "trainer": run.variant,
        "seed": run.seed,
        "steps": run.summaries[-1][1] if run.summaries else 0,
        "seconds": round(run.wall_s, 1),
        "reward_at": near,
        "first_at_or_above": first,
        "seconds_at_or_above": seconds,
        "update_size": stretches,
        "leftover_processes": run.leftovers,
        "first_brain": run.first_brain,
        "summaries": [(round(t, 1), step, value) for t, step, value in run.summaries],
    }


def medians(runs: list[dict[str, Any]], args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for trainer in dict.fromkeys(r["trainer"] for r in runs):
        mine = [r for r in runs if r["trainer"] == trainer]
        at = {m: [r["reward_at"][m] for r in mine if m in r["reward_at"]] for m in args.marks}
        first = {lv: [r["first_at_or_above"][lv] for r in mine] for lv in args.levels}
        out[trainer] = {
            "reward_at": {m: round(statistics.median(v), 3) for m, v in at.items() if v},
            "first_at_or_above": {
                lv: {
                    "reached": sum(s is not None for s in v),
                    "median_of_reached": statistics.median([s for s in v if s]) if any(v) else None,
                }
                for lv, v in first.items()
            },
        }
    return out


def main() -> int:
    stop_runs_on_sigterm()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="ppo/Pyramids.yaml", help="<trainer>/<Name>.yaml")
    parser.add_argument("--env", default="Pyramids", help="the unitysim environment")
    parser.add_argument("--seeds", type=int, nargs="+", default=[10, 11])
    parser.add_argument("--steps", type=int, default=540_000)
    parser.add_argument("--marks", type=int, nargs="*", default=[150_000, 300_000, 450_000])
    parser.add_argument("--spacing", type=int, default=30_000, help="the config's summary_freq")
    parser.add_argument("--levels", type=float, nargs="*", default=[0.5, 1.0])
    parser.add_argument(
        "--measure", choices=["reward", *MEASURES], default="reward", help="what a summary reads"
    )
    parser.add_argument(
        "--demo-steps", type=int, default=0, help="steps of unitysim's expert for demo_path"
    )
    parser.add_argument("--base-tree", type=Path, help="another commit's checkout, run too")
    parser.add_argument("--also-config", help="a second config (a variant), ours only")
    parser.add_argument("--behavior", help="read this behavior's summaries only (None: any)")
    parser.add_argument(
        "--ours-option", action="append", default=[], help="one more option of ours' train"
    )
    parser.add_argument(
        "--anchor-first-brain", help="self-play: mlagents-learn's first learning team's brain"
    )
    parser.add_argument("--anchor", type=Path, default=ANCHOR_DIR)
    parser.add_argument("--cap", type=float, default=1800.0, help="seconds: a safety stop")
    parser.add_argument("--work", type=Path, help="keep builds, logs and runs here")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-fixed-steps-"))
    work.mkdir(parents=True, exist_ok=True)
    build = build_player(args.env, work)
    args.anchor_hash_seed = (  # one for every seed: it depends on the names only
        hash_seed_putting_first(args, args.anchor_first_brain) if args.anchor_first_brain else None
    )
    args.config_path = with_demo(args.config, args.env, args.demo_steps, work)
    sides: list[Side] = [("ours", ROOT, args.config_path)]
    if args.base_tree:
        sides.append(("base", args.base_tree.resolve(), args.config_path))
    if args.also_config:
        also = with_demo(args.also_config, args.env, args.demo_steps, work)
        sides.append((f"ours-{Path(args.also_config).stem}", ROOT, also))
    runs: list[dict[str, Any]] = []
    for seed in args.seeds:
        anchor: list[dict[str, Any]] = []
        thread = threading.Thread(
            target=lambda s=seed, out=anchor: out.append(anchor_run(args, s, build, work))
        )
        thread.start()
        for side in sides:
            runs.append(our_run(args, seed, build, work, side))
            print(json.dumps(runs[-1]), flush=True)
        thread.join()
        runs += anchor
        print(json.dumps(anchor[0] if anchor else {"mlagents-learn": "failed", "seed": seed}))
    result = {
        "machine": machine(),
        "config": args.config,
        "ours_options": args.ours_option,
        "runs": runs,
    }
    result["medians"] = medians(runs, args)
    print(json.dumps(result["medians"], indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
