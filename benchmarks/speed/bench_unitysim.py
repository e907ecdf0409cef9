"""Is the unitysim stand-in ever what limits throughput? Measure it against a raw trainer.

Launches 3DBall through the real, unmodified ``mlagents_envs.UnityEnvironment`` (the stand-in
is a separate process, as a Unity build is), runs a random-action loop, and reports the
trainer's view (agent-steps/s, exchanges/s, round trip) next to what the stand-in costs: its
CPU time per exchange (``psutil`` on the launched process) and that time's share of the
round trip. The goal is a share of at most 25%: then the trainer, not the stand-in, is the
bottleneck. Resident memory of the stand-in is sampled too (``--minutes`` for a long run):
it must stay under 150 MB and not grow.

Both gRPC clients of the player are measured, interleaved (h2, grpcio, h2, grpcio, ...;
``--clients`` picks, ``--repeats`` sets how often), and each variant's best run is reported:
other load only ever slows a run down. ``--reference-encoder`` also runs the stand-in with
its reference (protobuf-object) encoder (``UNITYSIM_REFERENCE_ENCODER=1``), so that both
are measured on the same machine state and a ratio can be given; ``--physics C,numpy``
likewise runs 3DBall's C physics and its numpy twin (``UNITYSIM_PHYSICS=numpy``) side by
side. If GridWorld exists (camera PNGs on every step), it is launched too for a shorter
run, and its per-message step and encoding costs are measured in-process.

    .venv/bin/python -m benchmarks.speed.bench_unitysim [--seconds 20] [--reference-encoder]
        [--clients h2,grpcio] [--physics C,numpy] [--repeats 2] [--minutes 10]
        [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil

import mlagents_compat as compat

compat.install()

from mlagents_envs.environment import UnityEnvironment  # noqa: E402

from benchmarks.common import machine  # noqa: E402
from unitysim.envs.ball3d import compiled_physics  # noqa: E402
from unitysim.launcher import build  # noqa: E402

MB = 1024.0 * 1024.0
RSS_LIMIT_MB = 150.0
SHARE_GOAL = 0.25


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _cpu(process: psutil.Process) -> float:
    times = process.cpu_times()
    return times.user + times.system


def run_loop(
    directory: Path,
    env_name: str,
    seconds: float,
    warmup: float,
    reference: bool,
    client: str = "h2",
    physics: str = "C",
) -> dict[str, Any]:
    """One launch: warm up, then a timed random-action loop; the stand-in's costs around it."""
    variables = {"UNITYSIM_REFERENCE_ENCODER": "1" if reference else None}
    variables["UNITYSIM_PHYSICS"] = "numpy" if physics == "numpy" else None
    for key, value in variables.items():  # the player inherits them; none from our caller
        os.environ.pop(key, None)
        if value:
            os.environ[key] = value
    if physics != "numpy" and compiled_physics() is None:
        physics = "numpy"  # not built here: say so in the results
    try:
        env = UnityEnvironment(
            file_name=str(directory / env_name),
            base_port=free_port(),
            no_graphics=True,
            timeout_wait=10,
            additional_args=["--grpc-client", client],
        )
    finally:
        for key in variables:
            os.environ.pop(key, None)
    try:
        sim = psutil.Process(env._process.pid)  # the launcher execs: this is the player
        trainer = psutil.Process()
        env.reset()
        names = list(env.behavior_specs)

        def exchange() -> int:
            decisions = 0
            for name in names:
                steps, _ = env.get_steps(name)
                spec = env.behavior_specs[name]
                env.set_actions(name, spec.action_spec.random_action(len(steps)))
                decisions += len(steps)
            env.step()
            return decisions

        end = time.perf_counter() + warmup
        while time.perf_counter() < end:
            exchange()
        rss_start = sim.memory_info().rss / MB
        rss_max = rss_start
        rss_samples = [(0.0, rss_start)]
        sim_cpu0, trainer_cpu0 = _cpu(sim), _cpu(trainer)
        start = time.perf_counter()
        end = start + seconds
        next_sample = start + min(10.0, seconds / 4)
        exchanges = decisions = 0
        now = start
        while now < end:
            for _ in range(50):
                decisions += exchange()
            exchanges += 50
            now = time.perf_counter()
            if now >= next_sample:
                rss = sim.memory_info().rss / MB
                rss_max = max(rss_max, rss)
                rss_samples.append((round(now - start, 1), round(rss, 2)))
                next_sample = now + min(10.0, seconds / 4)
        elapsed = now - start
        sim_cpu, trainer_cpu = _cpu(sim) - sim_cpu0, _cpu(trainer) - trainer_cpu0
        rss_end = sim.memory_info().rss / MB
        rss_max = max(rss_max, rss_end)
    finally:
        env.close()
    round_trip = elapsed / exchanges
    return {
        "env": env_name,
        "client": client,
        "encoder": "reference" if reference else "fast",
        "physics": physics if env_name == "3DBall" else "-",
        "seconds": round(elapsed, 2),
        "exchanges": exchanges,
        "agent_steps_per_s": round(decisions / elapsed, 1),
        "exchanges_per_s": round(exchanges / elapsed, 1),
        "round_trip_ms": round(1e3 * round_trip, 4),
        "sim_cpu_ms_per_exchange": round(1e3 * sim_cpu / exchanges, 4),
        "sim_share_of_round_trip": round(sim_cpu / exchanges / round_trip, 4),
        "trainer_cpu_ms_per_exchange": round(1e3 * trainer_cpu / exchanges, 4),
        "sim_rss_mb_start": round(rss_start, 2),
        "sim_rss_mb_end": round(rss_end, 2),
        "sim_rss_mb_max": round(rss_max, 2),
        "rss_samples": rss_samples,
    }


def gridworld_available() -> str | None:
    """None if GridWorld can be played, else why not (it is written separately)."""
    try:
        from unitysim.envs import load

        load("GridWorld")
    except Exception as error:
        return f"{type(error).__name__}: {error}"
    return None


def gridworld_png_cost(seconds: float = 2.0) -> dict[str, Any]:
    """In-process: GridWorld steps and the encoding of their messages (PNG dominates)."""
    from unitysim import messages, wire
    from unitysim.envs import load
    from unitysim.envs.base import Actions, Parameters

    env_class = load("GridWorld")
    env = env_class(np.random.default_rng(0), 1, Parameters())
    behaviors = {b.name: b for b in env_class.behaviors}
    behavior = env_class.behaviors[0]
    rng = np.random.default_rng(1)
    output = env.reset()
    results: dict[str, Any] = {"agents": len(next(iter(output.values())))}
    encoders = {
        "fast": wire.encode_rl_output,
        "reference": lambda b, o, a: messages.rl_output(b, o, a).SerializeToString(),
    }
    for label, encode in encoders.items():
        count = 0
        step_s = encode_s = 0.0
        size = 0
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            n = len(output[behavior.name]) - int(output[behavior.name].done.sum())
            actions = {
                behavior.name: Actions(
                    np.zeros((n, 0), np.float32),
                    rng.integers(0, 5, size=(n, 1)).astype(np.int32),
                )
            }
            t0 = time.perf_counter()
            output = env.step(actions)
            t1 = time.perf_counter()
            size += len(encode(behaviors, output, []))
            t2 = time.perf_counter()
            step_s += t1 - t0
            encode_s += t2 - t1
            count += 1
        results[label] = {
            "step_ms": round(1e3 * step_s / count, 4),
            "encode_ms": round(1e3 * encode_s / count, 4),
            "message_bytes": size // count,
        }
    return results


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| env | client | encoder | physics | agent-steps/s | exchanges/s | round trip ms "
        "| stand-in CPU ms/exch | share | trainer CPU ms/exch "
        "| RSS start MB | RSS end MB | RSS max MB |"
    )
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for r in rows:
        lines.append(
            f"| {r['env']} | {r['client']} | {r['encoder']} | {r['physics']} "
            f"| {r['agent_steps_per_s']:,.0f} "
            f"| {r['exchanges_per_s']:,.0f} | {r['round_trip_ms']:.3f} "
            f"| {r['sim_cpu_ms_per_exchange']:.3f} | {100 * r['sim_share_of_round_trip']:.0f}% "
            f"| {r['trainer_cpu_ms_per_exchange']:.3f} | {r['sim_rss_mb_start']:.1f} "
            f"| {r['sim_rss_mb_end']:.1f} | {r['sim_rss_mb_max']:.1f} |"
        )
    return "\n".join(lines)


def ratios(rows: list[dict[str, Any]], axis: str, a: str, b: str) -> dict[str, dict]:
    """Side-by-side ratios a / b of rows that differ only in ``axis``."""
    keys = ("env", "client", "encoder", "physics")
    others = [k for k in keys if k != axis]
    found = {}
    for row in (r for r in rows if r[axis] == a):
        match = [r for r in rows if r[axis] == b and all(r[k] == row[k] for k in others)]
        if match:
            label = " ".join(str(row[k]) for k in others)
            found[label] = {
                key: round(row[key] / match[0][key], 3)
                for key in (
                    "agent_steps_per_s",
                    "sim_cpu_ms_per_exchange",
                    "sim_share_of_round_trip",
                )
            }
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="timed loop length")
    parser.add_argument("--minutes", type=float, help="long run (memory); overrides --seconds")
    parser.add_argument("--warmup", type=float, default=3.0, help="untimed seconds first")
    parser.add_argument("--env", default="3DBall", help="environment to launch")
    parser.add_argument(
        "--reference-encoder",
        action="store_true",
        help="also run with the reference protobuf-object encoder and report the ratio",
    )
    parser.add_argument(
        "--clients", default="h2,grpcio", help="player gRPC clients to compare (comma-separated)"
    )
    parser.add_argument(
        "--physics", default="C", help="3DBall physics to compare (comma-separated: C,numpy)"
    )
    parser.add_argument("--repeats", type=int, default=2, help="interleaved runs per variant")
    parser.add_argument("--no-gridworld", action="store_true", help="skip the PNG cost")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    seconds = 60.0 * args.minutes if args.minutes else args.seconds

    info = machine()
    print(
        f"# unitysim benchmark, {info['date']}: {info['nproc']} CPUs "
        f"({info['affinity']} usable), {info['cpu']}, Python {info['python']}"
    )
    grid_missing = "skipped (--no-gridworld)" if args.no_gridworld else gridworld_available()
    envs = [args.env] + ([] if grid_missing or args.env == "GridWorld" else ["GridWorld"])
    clients = [c.strip() for c in args.clients.split(",") if c.strip()]
    encoders = [False, True] if args.reference_encoder else [False]
    physics = [p.strip() for p in args.physics.split(",") if p.strip()]
    if not set(physics) <= {"C", "numpy"}:
        parser.error(f"--physics: {args.physics!r}: name C and/or numpy")
    runs = []
    with tempfile.TemporaryDirectory(prefix="bench-unitysim-") as tmp:
        directory = Path(tmp)
        build(directory, envs)
        for env_name in envs:
            length = seconds if env_name == args.env else min(seconds, 10.0)
            for _ in range(max(1, args.repeats)):
                for client in clients:
                    for reference in encoders:
                        for kind in physics if env_name == "3DBall" else physics[:1]:
                            run = run_loop(
                                directory, env_name, length, args.warmup, reference, client, kind
                            )
                            runs.append(run)
                            print(table([run]).splitlines()[-1], flush=True)
    best: dict[tuple[str, str, str, str], dict[str, Any]] = {}
    for run in runs:  # each variant's fastest run: other load only ever slows a run down
        key = (run["env"], run["client"], run["encoder"], run["physics"])
        if key not in best or run["agent_steps_per_s"] > best[key]["agent_steps_per_s"]:
            best[key] = run
    rows = list(best.values())
    print(f"\nbest of {max(1, args.repeats)} per variant:")
    print(table(rows))
    result: dict[str, Any] = {"machine": info, "best": rows, "runs": runs}
    fast = rows[0]
    for axis, a, b in (("encoder", "fast", "reference"), ("physics", "C", "numpy")):
        found = ratios(rows, axis, a, b)
        if found:
            result[f"ratio_{a}_over_{b}"] = found
            for label, ratio in found.items():
                print(f"\n{label}: {a} / {b} {axis}: {ratio}")
    growth = fast["sim_rss_mb_end"] - fast["sim_rss_mb_start"]
    verdict = {
        "share_ok": fast["sim_share_of_round_trip"] <= SHARE_GOAL,
        "rss_ok": fast["sim_rss_mb_max"] < RSS_LIMIT_MB,
        "rss_growth_mb": round(growth, 2),
    }
    result["verdict"] = verdict
    print(
        f"\nstand-in share ({fast['client']} client) "
        f"{100 * fast['sim_share_of_round_trip']:.0f}% "
        f"(goal <= {100 * SHARE_GOAL:.0f}%): {'ok' if verdict['share_ok'] else 'OVER'}; "
        f"RSS max {fast['sim_rss_mb_max']:.1f} MB (limit {RSS_LIMIT_MB:.0f}), "
        f"growth {growth:+.2f} MB over {fast['seconds']:.0f} s"
    )
    if grid_missing:
        result["gridworld_png"] = {"skipped": grid_missing}
        print(f"\nGridWorld: {grid_missing}")
    else:
        grid = gridworld_png_cost()
        result["gridworld_png"] = grid
        print(f"\nGridWorld messages, in-process (one area): {json.dumps(grid)}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
