"""The learner's memory per buffered sample, against the sample's raw bytes.

A behavior with one large vector observation (``--floats``, 91,700 by default: 367 KB
per agent step, near the gRPC message limit, as issue 18 tried) and PPO with
``--buffer-size``. The real ``CentralLearner`` runs alone in a child process (no Ray, no
Unity), as the learner actor does; segments arrive pickled, as workers send them
(numpy, observation and next observation per step). Reported, against ``buffer x raw``
(the raw bytes are the observation once, as mlagents-learn keeps it), from the child's
resident memory after its first, two-step segment:

- ``held``: resident memory the full buffer adds, just before the update;
- ``peak``: the process's peak resident memory over buffering and one update.

    .venv/bin/python -m benchmarks.costs.bench_learner_memory [--floats 91700] [--json F]

Per commit: from that tree's root, with this checkout on ``PYTHONPATH`` (``cd <tree> &&
PYTHONPATH=<this checkout> <this checkout>/.venv/bin/python -m
benchmarks.costs.bench_learner_memory``): the child imports the tree's learner.
"""

from __future__ import annotations

import argparse
import gc
import json
import multiprocessing
import resource
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
import psutil
from mlagents_envs.base_env import ActionSpec, BehaviorSpec, DimensionProperty, ObservationSpec
from mlagents_envs.base_env import ObservationType as Obs

from batches import keys
from batches.segment import Segment
from batches.specs import spec_to_dict
from benchmarks.common import machine
from benchmarks.speed.bench_learner import synthetic_segment


def segment(spec: BehaviorSpec, rows: int, horizon: int, rng: np.random.Generator) -> Segment:
    """A segment as a worker sends it: numpy, observation and next observation per step."""
    batch = synthetic_segment(spec, frozenset(), rows, horizon).exclude(*keys.METADATA)
    data = batch.apply(lambda t: t.numpy()).to_dict()
    size = spec.observation_specs[0].shape[0]
    n = rows * horizon
    data[keys.OBS]["vector"] = rng.random((n, size), dtype=np.float32)
    data[keys.NEXT][keys.OBS]["vector"] = rng.random((n, size), dtype=np.float32)
    return Segment("B?team=0", spec_to_dict(spec), data)


def learner_process(connection: Connection, floats: int, buffer_size: int) -> None:
    """The learner alone in its process, as the Ray actor is: what it holds is its own."""
    import torch

    from learners.host.learner import CentralLearner
    from learners.trainer_config.parse import parse_config

    torch.set_num_threads(1)
    config = parse_config(
        {
            "behaviors": {
                "B": {
                    "hyperparameters": {"buffer_size": buffer_size, "batch_size": 256},
                    "network_settings": {"hidden_units": 64, "num_layers": 2},
                }
            }
        }
    )
    learner = CentralLearner(config)
    process = psutil.Process()
    while (received := connection.recv()) is not None:
        learner.submit([received])
        del received
        gc.collect()
        connection.send((process.memory_info().rss, _peak(), learner.stats.updates))


def measure(floats: int, buffer_size: int, rows: int, horizon: int) -> dict[str, float]:
    sensor = ObservationSpec((floats,), (DimensionProperty.NONE,), Obs.DEFAULT, "vector")
    spec = BehaviorSpec([sensor], ActionSpec(2, ()))
    rng = np.random.default_rng(0)
    ours, theirs = multiprocessing.get_context("spawn").Pipe()
    child = multiprocessing.get_context("spawn").Process(
        target=learner_process, args=(theirs, floats, buffer_size)
    )
    child.start()
    try:
        ours.send(segment(spec, 1, 2, rng))  # builds the network and the buffer
        before, _, _ = ours.recv()
        steps, updates = 2, 0
        while steps + rows * horizon <= buffer_size:
            ours.send(segment(spec, rows, horizon, rng))
            held, buffering_peak, _ = ours.recv()
            steps += rows * horizon
        while not updates:
            ours.send(segment(spec, rows, horizon, rng))
            _, peak, updates = ours.recv()
        ours.send(None)
    finally:
        child.join(timeout=60)
        if child.is_alive():
            child.kill()
    raw = floats * 4
    return {
        "floats": floats,
        "buffer_size": buffer_size,
        "steps_held": steps,
        "held_per_sample": (held - before) / (steps * raw),
        "peak_per_buffered_sample": (peak - before) / (buffer_size * raw),
        "held_gb": (held - before) / 2**30,
        "peak_gb": (peak - before) / 2**30,
        "peak_gb_before_update": (buffering_peak - before) / 2**30,
    }


def _peak() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--floats", type=int, default=91_700)
    parser.add_argument("--buffer-size", type=int, default=2048)
    parser.add_argument("--rows", type=int, default=8, help="trajectories per segment")
    parser.add_argument("--horizon", type=int, default=64)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    result = {
        "machine": machine(),
        **measure(args.floats, args.buffer_size, args.rows, args.horizon),
    }
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
