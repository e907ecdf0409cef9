"""The docs' plots, drawn from the benchmarks' own result files (``benchmarks/results/``):

- ``docs/img/scaling.png`` from ``scaling.json`` (``speed/bench_scale.py``): agent steps/s
  delivered to the learner by workers, per learner, with the linear line from 1 worker;
- ``docs/img/learner-samples.png`` from ``learner.json`` (``speed/bench_learner.py``): PPO
  samples/s by network, one bar per device and precision (log scale);
- ``docs/img/learning-3DBall-vs-mlagents.png`` from ``vs-mlagents-3DBall-PPO.json``
  (``learning/bench_vs_mlagents.py``): mean reward by steps, mlagents-learn's runs beside
  ours, each seed a thin line.

A plot whose result file is missing is skipped, with one line saying so.

    .venv/bin/python -m benchmarks.plots [--results benchmarks/results] [--out docs/img]
"""

from __future__ import annotations

import argparse
import json
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks.common import RESULTS, ROOT

IMAGES = ROOT / "docs" / "img"
COLORS = {"counting": "tab:grey", "ppo": "tab:blue", "ppo+ahead": "tab:orange"}
LEARNER_NAMES = {
    "counting": "counting learner (routing only)",
    "ppo": "PPO, default",
    "ppo+ahead": "PPO, --collect-ahead",
}
VARIANTS = {  # bench_vs_mlagents's variants: panel title, colour
    "mlagents-learn": ("mlagents-learn 1.1.0", "tab:green"),
    "ours-mlagents-config": ("unity-rollout train, ML-Agents' config", "tab:blue"),
    "ours-shipped-config": ("unity-rollout train, shipped config", "tab:purple"),
}


def machine_text(result: dict[str, Any]) -> str:
    """The result's machine in words: as transcribed, or from ``common.machine``'s dict."""
    found = result.get("machine")
    if isinstance(found, dict):
        text = f"{found.get('nproc')} cores, {found.get('cpu')}"
        return text + (f", {found['gpu']}" if found.get("gpu") else "")
    return str(found or "machine not stated")


def caption(figure: Any, lines: list[str]) -> None:
    width = int(figure.get_figwidth() * 16)
    wrapped = [part for line in lines for part in textwrap.wrap(line, width)]
    figure.text(0.01, 0.01, "\n".join(wrapped), fontsize=7, va="bottom", ha="left")
    figure.subplots_adjust(bottom=0.12 + 0.028 * len(wrapped))


def scaling(result: dict[str, Any], out: Path) -> None:
    rows = result["best"]
    delay = result.get("args", {}).get("delay_ms")
    figure, axis = plt.subplots(figsize=(8, 5.5), dpi=110)
    for learner in sorted({r["learner"] for r in rows}, key=list(COLORS).index):
        points = sorted(
            (r["workers"], r["agent_steps_per_s"]) for r in rows if r["learner"] == learner
        )
        workers = [w for w, _ in points]
        color = COLORS.get(learner)
        label = LEARNER_NAMES.get(learner, learner)
        axis.plot(workers, [v for _, v in points], "o-", color=color, label=label)
        if workers[0] == 1:
            linear = [points[0][1] * w for w in workers]
            axis.plot(workers, linear, ":", color=color, linewidth=1)
    axis.plot([], [], ":", color="black", linewidth=1, label="linear: workers x its 1-worker rate")
    counts = sorted({r["workers"] for r in rows})
    axis.set_xticks(counts, [str(n) for n in counts])
    axis.set_xlim(0, counts[-1] * 1.05)
    axis.set_ylim(0, None)
    axis.yaxis.set_major_formatter(matplotlib.ticker.StrMethodFormatter("{x:,.0f}"))
    axis.set_xlabel("Ray workers (one unitysim 3DBall player each)")
    axis.set_ylabel("agent steps/s delivered to the learner")
    pace = f", every exchange {delay:g} ms late" if delay else ""
    axis.set_title(
        f"Scaling with workers: unitysim 3DBall{pace}\n{machine_text(result)}", fontsize=10
    )
    axis.grid(True, which="both", alpha=0.3)
    axis.legend(fontsize=8, loc="upper left")
    dates: dict[str, dict[str, list[str]]] = {}
    for r in sorted(rows, key=lambda r: r["workers"]):
        date = str(r.get("date", result["date"]))[:10]
        dates.setdefault(date, {}).setdefault(r["learner"], []).append(str(r["workers"]))
    when = "; ".join(
        f"{date}: " + ", ".join(f"{k} at {'/'.join(n)}" for k, n in which.items())
        for date, which in sorted(dates.items())
    )
    lines = [f"Measured {when} workers." if len(dates) > 1 else f"Measured {result['date'][:10]}."]
    lines.append(f"{result.get('command', '')}")
    if "source" in result:
        lines.append("Transcribed from docs/benchmarks.md (benchmarks/results/scaling.json).")
    caption(figure, lines)
    figure.savefig(out)
    plt.close(figure)


def network_name(row: dict[str, Any]) -> str:
    if row["encoder"] in ("-", "", None):
        return row["network"]
    return f"{row['network'].replace(' CNN', '')}\n{row['encoder']}"


def learner_samples(result: dict[str, Any], out: Path) -> None:
    rows = result["figures"]
    networks = list(dict.fromkeys(network_name(r) for r in rows))
    devices = list(dict.fromkeys(r["device"] for r in rows))
    variants = list(dict.fromkeys((r["device"], r["precision"]) for r in rows))
    figure, axis = plt.subplots(figsize=(10, 6), dpi=110)
    width = 0.8 / max(sum(network_name(r) == n for r in rows) for n in networks)
    colors = plt.get_cmap("tab10")
    labelled: set[tuple[str, str]] = set()
    for position, network in enumerate(networks):
        here = [r for r in rows if network_name(r) == network]
        here.sort(key=lambda r: variants.index((r["device"], r["precision"])))
        for index, r in enumerate(here):
            variant = (r["device"], r["precision"])
            bf16 = r["precision"] == "bfloat16"
            bars = axis.bar(
                position + width * (index - (len(here) - 1) / 2),
                r["samples_per_s"],
                width,
                color=colors(devices.index(r["device"])),
                alpha=0.55 if bf16 else 1.0,
                hatch="//" if bf16 else None,
                edgecolor="black",
                linewidth=0.4,
                label=None if variant in labelled else f"{r['device']}, {r['precision']}",
            )
            labelled.add(variant)
            label = f"{r['samples_per_s']:,.0f}"
            axis.bar_label(bars, [label], fontsize=6, rotation=90, padding=2)
    axis.set_yscale("log")
    axis.set_ylim(top=axis.get_ylim()[1] * 4)
    axis.set_xticks(range(len(networks)), networks)
    axis.set_ylabel("PPO samples/s (log scale)")
    axis.set_xlabel("network (3DBall MLP: config/3DBall.yaml; 84x84x3: config/AnimalArena.yaml)")
    axis.set_title(
        "Learner update throughput by network, device and precision\n"
        f"{machine_text(result)}; latest {result['date'][:10]}",
        fontsize=10,
    )
    axis.grid(True, axis="y", which="both", alpha=0.3)
    handles, names = axis.get_legend_handles_labels()
    order = [f"{device}, {precision}" for device, precision in variants]
    ranked = sorted(zip(handles, names, strict=True), key=lambda pair: order.index(pair[1]))
    axis.legend(*zip(*ranked, strict=True), fontsize=7, ncol=3, loc="upper right")
    dates = sorted({str(r.get("date", result["date"]))[:10] for r in rows})
    lines = [
        "samples/s: the steps an update trains on, each num_epoch times, per second of update. "
        "Hatched, lighter: bfloat16 (--mixed-precision).",
        f"Measured on {', '.join(dates)}; each bar's machine, date and commit are in "
        "benchmarks/results/learner.json.",
    ]
    if "source" in result:
        lines.append("Transcribed from docs/benchmarks.md. 2-core rows mix machines and dates.")
    else:
        lines.append(result.get("command", ""))
    caption(figure, lines)
    figure.savefig(out)
    plt.close(figure)


def learning_vs_mlagents(result: dict[str, Any], out: Path) -> None:
    runs = [r for r in result["runs"] if r.get("curve")]
    variants = [v for v in VARIANTS if any(r["variant"] == v for r in runs)]
    measure = {"group": "mean_group_reward", "elo": "elo"}.get(result.get("measure"), "mean_reward")
    figure, axes = plt.subplots(
        1, len(variants), figsize=(5 * len(variants), 5), dpi=110, sharey=True, squeeze=False
    )
    thousands = matplotlib.ticker.FuncFormatter(lambda x, _: f"{x / 1000:g}k")
    for axis, variant in zip(axes[0], variants, strict=True):
        title, color = VARIANTS[variant]
        mine = [r for r in runs if r["variant"] == variant]
        if variant != "mlagents-learn":  # mlagents-learn's seeds behind, for reference
            for index, run in enumerate(r for r in runs if r["variant"] == "mlagents-learn"):
                curve = run["curve"]
                label = "mlagents-learn's seeds" if index == 0 else None
                axis.plot(curve["step"], curve[measure], color="grey", alpha=0.35, label=label)
        for index, run in enumerate(mine):
            curve = run["curve"]
            label = "each seed" if index == 0 else None
            axis.plot(curve["step"], curve[measure], color=color, linewidth=0.9, label=label)
        for target in result.get("targets") or ():
            axis.axhline(target, color="black", linestyle="--", linewidth=0.7)
        axis.set_title(f"{title} ({len(mine)} seeds)", fontsize=9)
        axis.set_xlabel("agent steps")
        axis.xaxis.set_major_formatter(thousands)
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=7, loc="lower right")
    axes[0][0].set_ylabel(measure.replace("_", " ") + " (at each summary)")
    figure.suptitle(
        f"{result.get('case', '3DBall-PPO')}: mlagents-learn beside unity-rollout train, "
        f"each seed a line\n{machine_text(result)}; {result['date'][:10]}",
        fontsize=10,
    )
    caption(figure, [result.get("command", ""), "Dashed: the case's target level."])
    figure.subplots_adjust(top=0.82)
    figure.savefig(out)
    plt.close(figure)


PLOTS: dict[str, tuple[str, Callable[[dict[str, Any], Path], None]]] = {
    "scaling.png": ("scaling.json", scaling),
    "learner-samples.png": ("learner.json", learner_samples),
    "learning-3DBall-vs-mlagents.png": ("vs-mlagents-3DBall-PPO.json", learning_vs_mlagents),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=RESULTS, help="default: %(default)s")
    parser.add_argument("--out", type=Path, default=IMAGES, help="default: %(default)s")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for image, (name, draw) in PLOTS.items():
        source = args.results / name
        if not source.is_file():
            print(f"skipped {image}: no {source} (run {draw_source(name)} first)")
            continue
        draw(json.loads(source.read_text()), args.out / image)
        print(f"wrote {args.out / image} from {source}")


def draw_source(name: str) -> str:
    """The benchmark that writes result file ``name``."""
    if name.startswith("vs-mlagents-"):
        case = name.removeprefix("vs-mlagents-").removesuffix(".json")
        return f"python -m benchmarks.learning.bench_vs_mlagents --only {case}"
    return {
        "scaling.json": "python -m benchmarks.speed.bench_scale",
        "learner.json": "python -m benchmarks.speed.bench_learner",
    }[name]


if __name__ == "__main__":
    main()
