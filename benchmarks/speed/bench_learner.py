"""Learner update throughput: samples per second of PPO updates, per network and device.

Two networks: 3DBall's MLP (``config/3DBall.yaml``: 8 floats in, 2 continuous actions)
and an 84x84x3 camera plus a 3-float velocity with discrete actions (3, 3), AnimalAI's
shape (``config/AnimalArena.yaml``, ML-Agents' ``simple`` encoder; ``--encoders`` adds
others). Each runs on the CPU and, where this machine has one, on the GPU (``--devices``),
with and without mixed precision (``--mixed-precision``), in interleaved rounds; each
keeps its best round (other load only ever slows a run down).

The learner is the real ``CentralLearner`` in this process (no Ray, no Unity): synthetic
segments of the behavior's spec (uint8 cameras, as workers send them) fill its buffer,
and the update they trigger is timed. "samples/s" is the steps an update trains on per
second of update (each of them ``num_epoch`` times), as ``docs/benchmarks.md`` reports it.
The result goes to ``benchmarks/results/learner.json`` (``--json F``: to F), which
``benchmarks/plots.py`` draws.

    .venv/bin/python -m benchmarks.speed.bench_learner --rounds 2 [--devices cpu cuda] [--json F]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec, DimensionProperty, ObservationSpec
from mlagents_envs.base_env import ObservationType as Obs

from batches import keys
from batches.specs import spec_to_dict, step_spec
from benchmarks.common import RESULTS, record, save_result
from learners.host.devices import Compute
from learners.host.learner import CentralLearner
from learners.trainer_config.parse import CONFIG_DIR, load_config
from learners.trainer_config.settings import RunConfig

PLAIN = (DimensionProperty.NONE,)
IMAGE = (DimensionProperty.NONE, *(DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,) * 2)
QUESTION = "How fast is the learner, on CPU and on GPU? (PPO samples/s per network and device)"
CASES: dict[str, tuple[BehaviorSpec, str, frozenset[str]]] = {
    "3DBall MLP": (
        BehaviorSpec([ObservationSpec((8,), PLAIN, Obs.DEFAULT, "vector")], ActionSpec(2, ())),
        "3DBall.yaml",
        frozenset(),
    ),
    "84x84x3 CNN": (
        BehaviorSpec(
            [
                ObservationSpec((3, 84, 84), IMAGE, Obs.DEFAULT, "CameraSensor"),
                ObservationSpec((3,), PLAIN, Obs.DEFAULT, "Velocity"),
            ],
            ActionSpec(0, (3, 3)),
        ),
        "AnimalArena.yaml",
        frozenset({"CameraSensor"}),
    ),
}


def synthetic_segment(spec: BehaviorSpec, pixels: frozenset[str], rows: int, steps: int):
    """Well-formed packed rows of random data, cut at their last step (a horizon cut)."""
    n = rows * steps
    batch = step_spec(spec, pixels).expand(n).rand()
    cut = torch.zeros(n, 1, dtype=torch.bool)
    cut[steps - 1 :: steps] = True
    batch[keys.NEXT, keys.DONE], batch[keys.NEXT, keys.TRUNCATED] = cut, cut.clone()
    batch[keys.NEXT, keys.TERMINATED] = torch.zeros(n, 1, dtype=torch.bool)
    if spec.action_spec.discrete_branches:
        batch[keys.ACTION_MASK] = torch.ones_like(batch[keys.ACTION_MASK])
    batch[keys.POLICY_VERSION] = torch.zeros(n, dtype=torch.int64)
    batch[keys.LOG_PROB] = -torch.rand(n, batch[keys.LOG_PROB].shape[-1])
    batch.set_non_tensor(keys.BEHAVIOR, "B?team=0")
    batch.set_non_tensor(keys.SPEC, spec_to_dict(spec))
    return batch


def with_encoder(config: RunConfig, encoder: str) -> RunConfig:
    behaviors = {
        name: replace(s, network_settings=replace(s.network_settings, vis_encode_type=encoder))
        for name, s in config.behaviors.items()
    }
    default = replace(
        config.default,
        network_settings=replace(config.default.network_settings, vis_encode_type=encoder),
    )
    return replace(config, behaviors=behaviors, default=default)


def measure(
    case: str, encoder: str, compute: Compute, updates: int, busy: bool = False
) -> dict[str, float]:
    spec, config_file, pixels = CASES[case]
    config = load_config(CONFIG_DIR / config_file)
    settings = next(iter(config.behaviors.values()))  # the file's one behavior
    config = with_encoder(replace(config, behaviors={"B": settings}), encoder)
    learner = CentralLearner(config, compute=compute)
    rows, steps = 16, settings.time_horizon
    segments = [synthetic_segment(spec, pixels, rows, steps) for _ in range(4)]
    per_update = settings.hyperparameters.buffer_size // (rows * steps) + 1
    learner.submit([segments[0]])  # builds the network; warms up
    while learner.stats.updates < 1:
        learner.submit(segments[:1])
    started, samples0 = time.perf_counter(), learner.stats.samples
    seconds0 = learner.stats.update_seconds
    for index in range(updates * per_update):
        learner.submit([segments[index % len(segments)]])
    if compute.device != "cpu":
        torch.cuda.synchronize()
    result = {
        "samples_per_s": (learner.stats.samples - samples0)
        / (learner.stats.update_seconds - seconds0),
        "seconds": time.perf_counter() - started,
        "epochs": settings.hyperparameters.num_epoch,
        "buffer_size": settings.hyperparameters.buffer_size,
    }
    if busy and compute.device != "cpu":
        result["gpu_busy"] = gpu_busy(learner, segments)
    return result


def gpu_busy(learner: CentralLearner, segments: list[Any]) -> float:
    """The share of one update's wall time the GPU spends in kernels and copies
    (``torch.profiler``'s device time, as its tables total it): "SM busy while the learner
    updates", which nvidia-smi's samples cannot resolve for updates of tens of ms."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    algorithm = next(iter(learner.behaviors.values())).algorithm
    index = 0
    while not algorithm.ready():
        segment = segments[index % len(segments)]
        algorithm.add(segment, torch.zeros(segment.batch_size[0], dtype=torch.int64))
        index += 1
    cuda = torch.cuda.is_available()
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    sync()
    activities = [ProfilerActivity.CPU, *([ProfilerActivity.CUDA] if cuda else [])]
    with profile(activities=activities) as profiler:
        started = time.perf_counter()
        algorithm.update(0.5)
        sync()
        wall = time.perf_counter() - started
    events = profiler.key_averages()
    device_us = sum(e.self_device_time_total for e in events if e.device_type == DeviceType.CUDA)
    return device_us / 1e6 / wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--updates", type=int, default=2, help="timed updates per run")
    parser.add_argument("--devices", nargs="+", default=None, help="default: cpu, and cuda if any")
    parser.add_argument("--encoders", nargs="+", default=["simple"])
    parser.add_argument(
        "--mixed-precision",
        nargs="*",
        metavar="DEVICE",
        help="also runs with it on (on these devices; none named: on every one)",
    )
    parser.add_argument("--threads", type=int, default=None, help="torch threads (CPU)")
    parser.add_argument(
        "--gpu-busy", action="store_true", help="last round: the GPU's busy share of an update"
    )
    parser.add_argument(
        "--json", type=Path, default=RESULTS / "learner.json", help="the result file (%(default)s)"
    )
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    devices = args.devices or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    variants = [
        (case, encoder if case != "3DBall MLP" else "-", device, mixed)
        for case in CASES
        for encoder in (args.encoders if case != "3DBall MLP" else ["simple"])
        for device in devices
        for mixed in ([False, True] if mixed_on(args.mixed_precision, device) else [False])
    ]
    runs: dict[str, list[float]] = {}
    busy: dict[str, float] = {}
    envelope = record(
        QUESTION,
        torch_threads=torch.get_num_threads(),
        cuda=torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    )
    results: dict[str, Any] = {**envelope, **summary(runs, busy)}
    for round_ in range(args.rounds):
        for case, encoder, device, mixed in variants:
            name = f"{case} | {encoder} | {device}{' bf16' if mixed else ''}"
            compute = Compute.of(device, mixed)
            if mixed and not compute.mixed_precision:  # bfloat16 emulated: not measured
                print(f"{name}: skipped, {compute.note}", flush=True)
                continue
            profile = args.gpu_busy and round_ == args.rounds - 1
            result = measure(
                case, encoder if encoder != "-" else "simple", compute, args.updates, profile
            )
            runs.setdefault(name, []).append(result["samples_per_s"])
            print(f"{name}: {result['samples_per_s']:,.0f} samples/s", flush=True)
            if "gpu_busy" in result:
                busy[name] = result["gpu_busy"]
                print(f"{name}: GPU busy {result['gpu_busy']:.0%} of an update", flush=True)
            results = {**envelope, **summary(runs, busy)}
            # after every run: a stage cut short keeps what it measured
            save_result(args.json, results)
    best = results["best"]
    print(json.dumps(results, indent=2))
    print("\n| network | encoder | device | samples/s (best) | vs the CPU |")
    print("|---|---|---|---|---|")
    for name, value in best.items():
        case, encoder, device = name.split(" | ")
        cpu = best.get(f"{case} | {encoder} | cpu")
        ratio = f"{value / cpu:.1f}x" if cpu else "-"
        print(f"| {case} | {encoder} | {device} | {value:,.0f} | {ratio} |")


def mixed_on(devices: list[str] | None, device: str) -> bool:
    """``--mixed-precision`` as given: absent, with no device (every one), or some."""
    return devices is not None and (not devices or device in devices)


def summary(runs: dict[str, list[float]], busy: dict[str, float]) -> dict[str, Any]:
    """Every run's samples/s by variant (``network | encoder | device[ bf16]``), the best
    of each, the GPU's busy share, and the best as rows (``figures``, what the plot reads)."""
    best = {name: max(values) for name, values in runs.items()}
    return {"runs": runs, "best": best, "gpu_busy": busy, "figures": figures(best, busy)}


def figures(best: dict[str, float], busy: dict[str, float]) -> list[dict[str, Any]]:
    rows = []
    for name, value in best.items():
        network, encoder, variant = name.split(" | ")
        device = variant.removesuffix(" bf16")
        gpu = torch.cuda.get_device_name(device) if device.startswith("cuda") else None
        rows.append(
            {
                "network": network,
                "encoder": encoder,
                "device": gpu or f"CPU, {torch.get_num_threads()} threads",
                "precision": "bfloat16" if variant.endswith(" bf16") else "float32",
                "samples_per_s": round(value),
                "gpu_busy": busy.get(name),
            }
        )
    return rows


if __name__ == "__main__":
    main()
