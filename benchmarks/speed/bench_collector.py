"""``UnityCollector`` against torchrl's own ``UnityMLAgentsEnv``, the same policy on the same
unitysim 3DBall build (12 agents per instance): agent steps per second at 1, 2, 4 and 8
instances, with Unity answering at once and with every exchange ``--delay-ms`` late (real
Unity's pace). torchrl's side is its documented way to run several instances: a
``ParallelEnv`` of ``UnityMLAgentsEnv`` (one process and port each) under a
``Collector`` (its synchronous one); ours: one Ray worker per instance. Each run collects for
``--seconds`` after its first batch (start-up left out); the two alternate.

    .venv/bin/python -m benchmarks.speed.bench_collector --instances 1 2 4 8 --delays 0 40
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn

from benchmarks.common import ROOT, machine

FRAMES_PER_BATCH = 1200  # agent steps per batch (100 exchanges of one 3DBall)


def network() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(8, 64), nn.SiLU(), nn.Linear(64, 2), nn.Tanh())


class PerAgent(TensorDictModuleBase):
    """The same network over torchrl's per-agent keys: every agent's observation stacked,
    one forward, each agent's action written back."""

    def __init__(self, net: nn.Module, agents: list[tuple[str, str]], sensor: str) -> None:
        super().__init__()
        self.net, self.agents, self.sensor = net, agents, sensor
        self.in_keys = [(*a, sensor) for a in agents]
        self.out_keys = [(*a, "continuous_action") for a in agents]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = torch.stack([tensordict[key] for key in self.in_keys], dim=-2)
        with torch.no_grad():
            actions = self.net(obs)
        for index, key in enumerate(self.out_keys):
            tensordict[key] = actions[..., index, :]
        return tensordict


def build(work: Path) -> str:
    command = [str(ROOT / ".venv/bin/unity-rollout"), "unitysim", "build", str(work / "3DBall")]
    subprocess.run([*command, "--env", "3DBall"], check=True, capture_output=True)
    return str(work / "3DBall" / "3DBall.x86_64")


def rate(batches: object, seconds: float, count: object) -> float:
    """Agent steps per second after the first batch, for ``seconds``."""
    iterator = iter(batches)
    next(iterator)
    started, steps = time.perf_counter(), 0
    while time.perf_counter() - started < seconds:
        steps += count(next(iterator))
    return steps / (time.perf_counter() - started)


def torchrl_rate(
    player: str, instances: int, delay: float, seconds: float, port: int, frames: int
) -> float:
    from torchrl.collectors import Collector
    from torchrl.envs import ParallelEnv, SerialEnv, UnityMLAgentsEnv

    def make(index: int) -> UnityMLAgentsEnv:
        import mlagents_compat  # noqa: F401  (a spawned process: mlagents-envs on protobuf 7)

        extra = ["--sim-delay-ms", str(delay)]
        return UnityMLAgentsEnv(
            file_name=player, worker_id=index, base_port=port, no_graphics=True,
            additional_args=extra,
        )  # fmt: skip

    makers = [partial(make, i) for i in range(instances)]
    env = SerialEnv(1, makers) if instances == 1 else ParallelEnv(instances, makers)
    agents = [k[:2] for k in env.observation_spec.keys(True, True) if len(k) == 3]
    sensor = next(k[2] for k in env.observation_spec.keys(True, True) if len(k) == 3)
    policy = PerAgent(network(), sorted(set(agents)), sensor)
    per_step = len(set(agents))
    collector = Collector(env, policy, frames_per_batch=max(1, frames // per_step), total_frames=-1)
    try:
        return rate(collector, seconds, lambda batch: batch.numel() * per_step)
    finally:
        collector.shutdown()
        env.close(raise_if_closed=False)


def ours_rate(player: str, instances: int, delay: float, seconds: float, frames: int) -> float:
    from rollout.environment.unity import UnityConfig
    from torchrl_adapters import UnityCollector

    policy = TensorDictModule(network(), in_keys=["observation"], out_keys=["action"])
    unity = UnityConfig(player, additional_args=("--sim-delay-ms", str(delay)))
    collector = UnityCollector(
        player, policy, frames, behavior="3DBall", num_workers=instances,
        worker_cpus=min(1.0, 2 / instances), unity=unity,
    )  # fmt: skip
    try:
        return rate(collector, seconds, lambda batch: batch.numel())
    finally:
        collector.shutdown()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--instances", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--delays", type=float, nargs="+", default=[0.0, 40.0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument(
        "--per-instance",
        action="store_true",
        help=f"{FRAMES_PER_BATCH} agent steps per batch for each instance (a rollout of "
        "100 exchanges per instance, as on-policy runs size theirs), not for all",
    )
    parser.add_argument("--only", choices=["ours", "torchrl"], help="run one side only")
    parser.add_argument("--json", help="write the results here too")
    args = parser.parse_args()
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    report: dict = {"machine": machine(), "runs": []}
    try:
        with tempfile.TemporaryDirectory(prefix="bench-collector-") as tmp:
            player = build(Path(tmp))
            for delay in args.delays:
                for instances in args.instances:
                    frames = FRAMES_PER_BATCH * (instances if args.per_instance else 1)
                    ours = theirs = float("nan")
                    if args.only != "torchrl":
                        ours = ours_rate(player, instances, delay, args.seconds, frames)
                    if args.only != "ours":
                        theirs = torchrl_rate(player, instances, delay, args.seconds, 35000, frames)
                    row = {
                        "delay_ms": delay,
                        "instances": instances,
                        "frames_per_batch": frames,
                        "ours": round(ours, 1),
                        "torchrl": round(theirs, 1),
                        "ratio": round(ours / theirs, 2),
                    }
                    print(json.dumps(row), flush=True)
                    report["runs"].append(row)
    finally:
        ray.shutdown()
    for delay in args.delays:
        rows = [r for r in report["runs"] if r["delay_ms"] == delay]
        base = rows[0]["ours"] / rows[0]["instances"]
        for row in rows:
            row["ours_of_linear"] = round(row["ours"] / (base * row["instances"]), 2)
        print(f"delay {delay:g} ms: ours of linear", [r["ours_of_linear"] for r in rows])
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
