"""Does mlagents-learn's acting normalizer, moved by every trajectory as it arrives, buy it
steps? mlagents-learn 1.1.0 on 3DBall with ML-Agents' ``ppo/3DBall.yaml``, per seed as it
is and with its acting policy holding the normalizer of its last update (as our workers
do), interleaved; steps to the first summary >= 90.

    .venv/bin/python -m benchmarks.equality.bench_mlagents_normalizer --seeds 0 1 2 [--json F]

The frozen side runs mlagents-learn through this file, by its path under the anchor's own
Python (``wrap``: nothing of ours is imported there but ``mlagents_hooks.py`` beside it):
``TorchPolicy.get_action`` reads a copy of the actor's normalizer taken at the end of each
``_update_policy``, while ``_process_trajectory`` goes on updating the live one for the
values and the next update. Nothing in site-packages is edited.
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any


def freeze_acting_normalizer() -> None:
    """Runs inside mlagents-learn (its own venv): acting reads the last update's copy."""
    from mlagents.trainers.policy import torch_policy
    from mlagents.trainers.torch_entities.encoders import Normalizer
    from mlagents.trainers.trainer import on_policy_trainer

    frozen: dict[int, tuple[Any, Any, Any]] = {}
    fields = ("normalization_steps", "running_mean", "running_variance")

    def normalizers(policy: Any) -> list[Any]:
        return [m for m in policy.actor.modules() if isinstance(m, Normalizer)]

    def copy(normalizer: Any) -> tuple[Any, Any, Any]:
        return tuple(getattr(normalizer, f).clone() for f in fields)  # type: ignore[return-value]

    get_action = torch_policy.TorchPolicy.get_action

    def acting(self: Any, *args: Any, **kwargs: Any) -> Any:
        found = normalizers(self)
        live = [tuple(getattr(n, f) for f in fields) for n in found]
        for n in found:
            for name, value in zip(fields, frozen.setdefault(id(n), copy(n)), strict=True):
                setattr(n, name, value)
        try:
            return get_action(self, *args, **kwargs)
        finally:
            for n, values in zip(found, live, strict=True):
                for name, value in zip(fields, values, strict=True):
                    setattr(n, name, value)

    update = on_policy_trainer.OnPolicyTrainer._update_policy

    def updated(self: Any) -> Any:
        result = update(self)
        for n in normalizers(self.policy):
            frozen[id(n)] = copy(n)
        return result

    torch_policy.TorchPolicy.get_action = acting
    on_policy_trainer.OnPolicyTrainer._update_policy = updated
    print("[bench_mlagents_normalizer] acting reads the last update's normalizer", flush=True)


def main() -> int:
    from benchmarks.common import machine, mlagents_config  # our venv from here on
    from benchmarks.learning.trainer_runs import (
        ANCHOR_DIR,
        Run,
        anchor_command,
        build_player,
        run_command,
        stop_runs_on_sigterm,
    )

    stop_runs_on_sigterm()

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--anchor", type=Path, default=ANCHOR_DIR)
    parser.add_argument("--steps", type=int, default=132_000, help="a run short of 90 stops here")
    parser.add_argument("--work", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-mlagents-normalizer-"))
    work.mkdir(parents=True, exist_ok=True)
    build = build_player("3DBall", work)
    python = str(args.anchor / "venv/bin/python")
    launcher = str(args.anchor / "mlagents_learn_launcher.py")
    sides = {"as is": [python, launcher], "frozen": [python, __file__, "wrap", launcher]}
    runs: list[dict[str, Any]] = []
    for seed in args.seeds:
        order = list(sides) if seed % 2 == 0 else list(sides)[::-1]
        for side in order:
            run_id = f"{side.replace(' ', '-')}-{seed}"
            command = anchor_command(
                sides[side], mlagents_config("ppo/3DBall.yaml"), build, run_id, work / "mlagents",
                31000 + 10 * seed, seed,
            )  # fmt: skip
            run = Run(side, seed)
            env = {"PYTHONPATH": str(args.anchor / "shim")}
            log = work / f"{run_id}.log"
            run_command(command, env, run, signal.SIGTERM, log, 90.0, 600, stop_step=args.steps)
            hit = run.reached(90.0)
            runs.append({"side": side, "seed": seed, "steps_to_90": hit and hit[1]})
            print(json.dumps(runs[-1]), flush=True)
    summary = {
        side: statistics.median(r["steps_to_90"] or args.steps for r in runs if r["side"] == side)
        for side in sides
    }
    print(json.dumps({"median_steps_to_90 (not reached: --steps)": summary}))
    if args.json:
        args.json.write_text(json.dumps({"machine": machine(), "runs": runs, "median": summary}))
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["wrap"]:  # under the anchor's Python: mlagents-learn, patched
        from mlagents_hooks import run_patched  # run as a file: this folder is sys.path[0]

        run_patched(freeze_acting_normalizer, sys.argv[2], sys.argv[2:])
    else:
        sys.exit(main())
