"""mlagents-learn against ``unity-rollout train``, side by side: same unitysim build, same
ML-Agents YAML, 2 Unity instances each, the runs of a round interleaved, several seeds.

Each case names ML-Agents' own config (``tests/mlagents_configs/``) and our shipped
one (``config/``). A round runs, one after the other on the same build: mlagents-learn with
ML-Agents' config, ``unity-rollout train`` with the same file, and ``unity-rollout train``
with the shipped config. Every run is stopped once its summaries reached every target
level (or at the case's cap). Reported per run, counted from process start: steps and
seconds to each target level (the first summary whose mean reward reaches it, as
mlagents-learn prints them), the first environment step and the first summary; per
round, the ratios to mlagents-learn. Each case's result, with every run's learning curve
(steps, wall seconds and mean reward at each summary), goes to
``benchmarks/results/vs-mlagents-<case>.json`` (``--results DIR`` elsewhere), which
``benchmarks/plots.py`` draws.

mlagents-learn 1.1.0 runs from the anchor recipe's work directory (``--anchor``, default
``$MLAGENTS_ANCHOR`` or ``/tmp/mlbench``): its ``venv/``, ``shim/`` and
``mlagents_learn_launcher.py``, which ``run_mlagents_learn.sh`` of the anchor recipe
creates (see docs/benchmarks.md). Every process a run starts is found by an environment
tag and ended when the run ends.

    .venv/bin/python -m benchmarks.learning.bench_vs_mlagents --only 3DBall-PPO --seeds 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import statistics
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from benchmarks.common import RESULTS, ROOT, machine, record, save_result
from benchmarks.learning.trainer_runs import (
    ANCHOR_DIR,
    Run,
    anchor_command,
    build_player,
    our_command,
    run_command,
    stop_runs_on_sigterm,
    with_demo,
)

# the variants of a round: mlagents-learn and ours with ML-Agents' config, ours with ours
ANCHOR, OURS_MLAGENTS, OURS_SHIPPED = (
    "mlagents-learn",
    "ours-mlagents-config",
    "ours-shipped-config",
)


@dataclass(frozen=True)
class Case:
    name: str
    env: str  # unitysim environment, built as a player for both trainers
    mlagents_config: str  # benchmarks.common.mlagents_config's name
    shipped_config: str | None  # in config/; None: no shipped config for this example
    targets: tuple[float, ...]  # reward levels, ascending; () : mlagents-learn's end level
    cap_s: float  # a run not there by then is stopped and reported as not reaching it
    measure: str = "reward"  # or "group" (POCA's mean group reward), "elo" (self-play)
    behavior: str | None = None  # read this behavior's summary lines only (None: any)
    # steps of unitysim's scripted expert recorded by ``record-demo`` for the config's
    # demo_path (GAIL's, behavioral cloning's), given to both trainers; 0: none
    demo_steps: int = 0
    held: int = 1  # summaries a level must hold for, on average (trainer_runs.Run.held)


CASES = (
    Case("3DBall-PPO", "3DBall", "ppo/3DBall.yaml", "3DBall.yaml", (90.0,), 600),
    Case("3DBall-SAC", "3DBall", "sac/3DBall.yaml", "3DBall_sac.yaml", (90.0,), 900),
    Case("Basic-PPO", "Basic", "ppo/Basic.yaml", "Basic.yaml", (0.9,), 300),
    Case(
        "GridWorld-PPO", "GridWorld", "ppo/GridWorld.yaml", "GridWorld.yaml", (0.0, 0.3, 0.8), 600
    ),
    # environment parameters: the ball's mass and scale resampled (ML-Agents' samplers)
    Case("3DBall_randomize-PPO", "3DBall", "ppo/3DBall_randomize.yaml", None, (50.0, 90.0), 900),
    # a group reward for escaping, a knight sacrificed on the way: POCA
    Case(
        "DungeonEscape-POCA",
        "DungeonEscape",
        "poca/DungeonEscape.yaml",
        "DungeonEscape.yaml",
        (0.1, 0.5),
        3600,
        measure="group",
    ),
    # a sparse reward, ML-Agents' intrinsic signals: curiosity, RND (to mlagents-learn's end)
    Case("Pyramids-PPO-curiosity", "Pyramids", "ppo/Pyramids.yaml", None, (), 900),
    Case("PyramidsRND-PPO", "Pyramids", "ppo/PyramidsRND.yaml", None, (), 900),
    # the curiosity config without its curiosity section, to show what curiosity does
    Case("Pyramids-PPO-no-curiosity", "Pyramids", "ppo/Pyramids_nocuriosity.yaml", None, (), 900),
    # memory (an LSTM) on a Hallway whose symbol is out of sight from the goals; and the
    # same config without memory, to show what it does
    Case("Hallway-PPO-memory", "Hallway", "ppo/Hallway.yaml", None, (), 1800, held=3),
    Case("Hallway-PPO-no-memory", "Hallway", "ppo/Hallway_nomemory.yaml", None, (), 1800, held=3),
    # a sparse reward behind a wall: whether and when the policy first finds the goal
    # varies from seed to seed in both trainers (SmallWallJump: no wall or a small one)
    Case(
        "SmallWallJump-PPO",
        "WallJump",
        "ppo/WallJump.yaml",
        None,
        (0.5,),
        480,
        behavior="SmallWallJump",
    ),
    # self-play, ML-Agents' configs: ELO, to the level mlagents-learn ends its run at
    Case("SoccerTwos-POCA", "SoccerTwos", "poca/SoccerTwos.yaml", None, (), 900, "elo"),
    Case(
        "StrikersVsGoalie-POCA",
        "StrikersVsGoalie",
        "poca/StrikersVsGoalie.yaml",
        None,
        (),
        900,
        "elo",
        "Striker",  # only goals end a game: the Striker's ELO climbs, the Goalie's falls
    ),
    # ML-Agents' imitation configs (GAIL, behavioral cloning), on a recording of
    # unitysim's expert made by our recorder, the same file for both trainers
    Case(
        "Pyramids-imitation", "Pyramids", "imitation/Pyramids.yaml", None, (), 900, demo_steps=5000
    ),
    Case(
        "Hallway-imitation",
        "Hallway",
        "imitation/Hallway.yaml",
        None,
        (),
        900,
        demo_steps=5000,
        held=3,
    ),
)


def anchor_run(
    case: Case, seed: int, build: Path, config: Path, anchor: Path, work: Path, port: int
) -> Run:
    run = Run(ANCHOR, seed, held=case.held)
    prefix = [str(anchor / "venv/bin/python"), str(anchor / "mlagents_learn_launcher.py")]
    command = anchor_command(
        prefix, config, build, f"ml-{case.name}-{seed}", work / "mlagents", port, seed
    )
    env = {"PYTHONPATH": str(anchor / "shim"), "MLBENCH_MARKS": "1"}
    log = work / f"ml-{case.name}-{seed}.log"
    stop_at = levels(case, None)[-1]
    run_command(command, env, run, signal.SIGTERM, log, stop_at, *reading(case))
    return run


def our_run(
    case: Case, seed: int, build: Path, config: Path, variant: str, work: Path, stop_at: float
) -> Run:
    run = Run(variant, seed, held=case.held)
    run_id = f"ours-{case.name}-{'ml' if variant == OURS_MLAGENTS else 'shipped'}-{seed}"
    prefix = [str(ROOT / ".venv/bin/unity-rollout"), "train"]
    command = our_command(prefix, config, build, run_id, work / "ours", seed, case.cap_s + 30)
    log = work / f"{run_id}.log"
    run_command(command, {}, run, signal.SIGINT, log, stop_at, *reading(case))
    summary = work / "ours" / run_id / "summary.json"
    if summary.is_file():  # the moment its first worker's Unity answered
        first_step = json.loads(summary.read_text()).get("startup", {}).get("first_step_at")
        if first_step is not None:
            run.first_step_s = round(first_step - run.launched_at, 2)
    return run


def reading(case: Case) -> tuple[float, str, str | None]:
    return case.cap_s, case.measure, case.behavior


CURVE_COLUMNS = {"reward": "mean_reward", "group": "mean_group_reward", "elo": "elo"}


def curve(case: Case, run: Run) -> dict[str, list[float]]:
    """A run's learning curve, one point per summary: steps, wall seconds from its
    launch, and the case's measure (the mean reward; POCA's group reward; ELO)."""
    return {
        "step": [step for _, step, _ in run.summaries],
        "wall_s": [round(seconds, 2) for seconds, _, _ in run.summaries],
        CURVE_COLUMNS[case.measure]: [value for _, _, value in run.summaries],
    }


def ratio(ours: Run, anchor: Run, level: float, index: int) -> float | None:
    mine, theirs = ours.reached(level), anchor.reached(level)
    return None if mine is None or theirs is None else round(mine[index] / theirs[index], 2)


def levels(case: Case, anchor: Run | None) -> tuple[float, ...] | tuple[None]:
    """The levels a round measures: the case's targets, or the level mlagents-learn's run
    ended at (its last ``held`` summaries; None before it ran, or when it printed none)."""
    if case.targets:
        return case.targets
    return (anchor.end_level() if anchor is not None else None,)


def print_round(case: Case, runs: list[Run]) -> None:
    anchor = runs[0]
    for run in runs:
        if not run.summaries and run.log is not None:  # it failed: show why
            tail = run.log.read_text().splitlines()[-5:]
            print(
                f"{case.name} seed {run.seed} {run.variant} exited {run.exit_code}:",
                *tail,
                sep="\n  ",
            )
        cells = []
        for level in levels(case, anchor):
            if level is None:
                cells.append("mlagents-learn reached no summary")
                continue
            hit = run.reached(level)
            text = "not reached" if hit is None else f"{hit[1]:,} steps, {hit[0]:.0f} s"
            if run is not anchor:
                steps, seconds = ratio(run, anchor, level, 1), ratio(run, anchor, level, 0)
                text += f" (steps x{steps}, time x{seconds})"
            cells.append(f"{level:g}: {text}")
        print(
            f"{case.name} seed {run.seed} | {run.variant:<20} | {'; '.join(cells)} | first step "
            f"{run.first_step_s} s, first summary "
            f"{run.summaries[0][0] if run.summaries else float('nan'):.1f} s",
            flush=True,
        )


def medians(case: Case, rounds: list[list[Run]]) -> dict:
    """Per variant and level (the anchor's end level: its own in each round): median steps
    and seconds, and median ratios to the anchor."""
    out: dict = {}
    for column in range(1, len(rounds[0])):
        variant = rounds[0][column].variant
        per_level = {}
        for index, name in enumerate(map(str, case.targets or ("mlagents-learn's end",))):
            at = [(r, level) for r in rounds if (level := levels(case, r[0])[index]) is not None]
            steps = [r[column].reached(level) for r, level in at]
            step_ratios = [x for r, level in at if (x := ratio(r[column], r[0], level, 1))]
            time_ratios = [x for r, level in at if (x := ratio(r[column], r[0], level, 0))]
            per_level[name] = {
                "reached": sum(hit is not None for hit in steps),
                "rounds": len(rounds),
                "median_step_ratio": statistics.median(step_ratios) if step_ratios else None,
                "median_time_ratio": statistics.median(time_ratios) if time_ratios else None,
            }
        out[variant] = per_level
    return out


def main() -> int:
    stop_runs_on_sigterm()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", default=[], help="case names (e.g. 3DBall-PPO)")
    parser.add_argument("--seeds", type=int, default=3, help="rounds, one seed each (>= 2)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--anchor", type=Path, default=ANCHOR_DIR)
    parser.add_argument(
        "--skip",
        nargs="*",
        default=[],
        choices=[OURS_MLAGENTS, OURS_SHIPPED],
        help="our variants to leave out",
    )
    parser.add_argument(
        "--cap", type=float, help="seconds before a run is stopped (default: the case's)"
    )
    parser.add_argument("--json", help="write every case's results here too, in one file")
    parser.add_argument(
        "--results",
        type=Path,
        default=RESULTS,
        help="each case's result file goes here, as vs-mlagents-<case>.json (default: %(default)s)",
    )
    parser.add_argument("--work", help="keep builds, logs and run directories here")
    args = parser.parse_args()
    anchor = args.anchor
    if not (anchor / "mlagents_learn_launcher.py").is_file():
        print(
            f"error: no mlagents-learn anchor in {anchor}: run the anchor recipe's "
            "run_mlagents_learn.sh once with WORKDIR there",
            file=sys.stderr,
        )
        return 2
    report: dict = {"machine": machine(), "cases": []}
    with tempfile.TemporaryDirectory(prefix="bench-vs-mlagents-") as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        for case in CASES:
            if args.only and case.name not in args.only:
                continue
            if args.cap:
                case = dataclasses.replace(case, cap_s=args.cap)
            build = build_player(case.env, work)
            mlagents_config = with_demo(case.mlagents_config, case.env, case.demo_steps, work)
            rounds = []
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                port = 31000 + 10 * seed
                runs = [anchor_run(case, seed, build, mlagents_config, anchor, work, port)]
                shipped = case.shipped_config
                for variant, config in (
                    (OURS_MLAGENTS, mlagents_config),
                    (OURS_SHIPPED, ROOT / "config" / shipped if shipped else None),
                ):
                    if variant not in args.skip and config is not None:
                        stop_at = levels(case, runs[0])[-1]
                        runs.append(our_run(case, seed, build, config, variant, work, stop_at))
                print_round(case, runs)
                rounds.append(runs)
            report["cases"].append(
                {
                    "case": case.name,
                    "env": case.env,
                    "mlagents_config": case.mlagents_config,
                    "shipped_config": case.shipped_config,
                    "targets": case.targets,
                    "measure": case.measure,
                    "runs": [
                        {**run.report(levels(case, runs[0])), "curve": curve(case, run)}
                        for runs in rounds
                        for run in runs
                    ],
                    "medians": medians(case, rounds),
                }
            )
            print(json.dumps(report["cases"][-1]["medians"]), flush=True)
            question = f"{case.name}: does unity-rollout train learn as fast as mlagents-learn?"
            saved = save_result(
                args.results / f"vs-mlagents-{case.name}.json",
                record(question, **report["cases"][-1]),
            )
            print(f"wrote {saved}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
