"""Our ``.demo`` files read by ML-Agents' own loader, and ML-Agents-written files read by ours.

Both directions, every field compared (spec, summary, and per step: observations, reward,
done, max_step_reached, agent id, group id and reward, action mask, continuous and discrete
actions; and the rows ``demo_to_buffer`` builds for BC and GAIL):

* ours -> ML-Agents: cases written with ``demonstrations.write_demo`` (discrete actions with
  masks, continuous, hybrid with rank-2 and float image sensors, PNG images, a directory of
  two files) are loaded in the anchor venv by ``mlagents.trainers.demo_loader``
  (``load_demonstration``, ``steps_from_proto`` on each record as ``make_demo_buffer`` does,
  and ``demo_to_buffer``); what it read comes back as ``.npz`` files.
* ML-Agents -> ours: the anchor side writes files with ML-Agents' Python ``write_demo``
  (protos filled as Unity's C# ``GrpcExtensions`` fills them, most with Unity's trailing
  metadata copy, one in the old format with only deprecated action fields), and reads them
  itself; we read them with ``demonstrations.read_demo`` and compare.
* ``--real FILE``: Unity-recorded files, read by both.

ML-Agents' side (``demo_mlagents_side.py``) runs in the anchor recipe's venv (``--anchor``,
as ``bench_vs_mlagents.py``) with the launcher's runtime workarounds.

    .venv/bin/python -m benchmarks.equality.check_demo_vs_mlagents [--real Recorded.demo ...]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import ROOT
from benchmarks.equality.demo_mlagents_side import FIELDS

# run by the anchor's own Python as a file (it imports nothing of ours)
SIDE = ROOT / "benchmarks" / "equality" / "demo_mlagents_side.py"


def our_cases(work: Path) -> dict[str, object]:
    """Written with our writer: the demonstrations the tests use, and a directory of two."""
    from demonstrations import write_demo
    from tests.demonstrations import samples  # tests/ is not installed: run from the root

    written = {}
    (work / "ours").mkdir()
    for name in ("DISCRETE", "CONTINUOUS", "HYBRID", "IMAGES"):
        demo = samples.demonstration(getattr(samples, name), count=13, pixels=True)
        write_demo(
            work / "ours" / f"{name.lower()}.demo", demo, png=[0, 1, 2] if name == "IMAGES" else []
        )
        written[name.lower()] = demo
    (work / "ours_dir").mkdir()
    for seed, file in enumerate(("one.demo", "two.demo")):
        demo = samples.demonstration(samples.DISCRETE, count=6 + seed, seed=seed)
        write_demo(work / "ours_dir" / file, demo)
    return written


def differences(demo, theirs) -> list[str]:
    """Every field of our reading against ML-Agents' reading of the same file(s)."""
    from mlagents_envs.base_env import DimensionProperty

    import mlagents_compat  # noqa: F401

    wrong = []
    spec = json.loads(str(theirs["spec"]))
    ours_sensors = [
        {
            "shape": list(o.shape),
            "dims": [int(DimensionProperty(d)) for d in o.dimension_property],
            "type": o.observation_type.value,
            "name": o.name,
        }
        for o in demo.behavior_spec.observation_specs
    ]
    actions = demo.behavior_spec.action_spec
    if spec != {
        "sensors": ours_sensors,
        "continuous": actions.continuous_size,
        "branches": list(actions.discrete_branches),
    }:
        wrong.append(f"spec {spec} vs ours {demo.behavior_spec}")
    if "meta" in theirs:
        name, steps, episodes, mean = json.loads(str(theirs["meta"]))
        m = demo.meta
        if [name, steps or len(demo.steps), episodes, np.float32(mean)] != [
            m.name,
            m.steps,
            m.episodes,
            np.float32(m.mean_reward),
        ]:
            wrong.append(f"meta {name, steps, episodes, mean} vs ours {m}")
    steps = demo.steps
    if len(steps) != int(theirs["total"]) and int(theirs["total"]):
        wrong.append(f"{int(theirs['total'])} steps vs ours {len(steps)}")
    if len(steps) != len(theirs["reward"]):
        return [*wrong, f"{len(theirs['reward'])} records vs ours {len(steps)}"]
    mine = {
        "reward": [np.float32(s.reward) for s in steps],
        "done": [s.done for s in steps],
        "max_step": [s.interrupted for s in steps],
        "agent_id": [s.agent_id for s in steps],
        "group_id": [s.group_id for s in steps],
        "group_reward": [np.float32(s.group_reward) for s in steps],
    }
    for name in FIELDS:
        if not np.array_equal(
            np.asarray(mine[name]), theirs[name].astype(np.asarray(mine[name]).dtype)
        ):
            wrong.append(f"{name} differs")
    for name, get in (
        ("mask", "action_mask"),
        ("continuous", "continuous"),
        ("discrete", "discrete"),
    ):
        for k, (s, t) in enumerate(zip(steps, theirs[name], strict=True)):
            if not np.array_equal(getattr(s, get), np.asarray(t, getattr(s, get).dtype)):
                wrong.append(f"step {k} {name}: {t} vs ours {getattr(s, get)}")
    for i in range(len(ours_sensors)):
        if not np.array_equal(np.stack([s.observations[i] for s in steps]), theirs[f"obs_{i}"]):
            wrong.append(f"observation {i} differs")
    # demo_to_buffer: each step but the last, with the next step's done and reward
    rows = {
        "buffer_done": [s.done for s in steps[1:]],
        "buffer_reward": [np.float32(s.reward) for s in steps[1:]],
        **{
            f"buffer_obs_{i}": [s.observations[i] for s in steps[:-1]]
            for i in range(len(ours_sensors))
        },
        **(
            {"buffer_continuous": [s.continuous for s in steps[:-1]]}
            if actions.continuous_size
            else {}
        ),
        **({"buffer_discrete": [s.discrete for s in steps[:-1]]} if actions.discrete_size else {}),
    }
    for key, values in rows.items():
        if not np.array_equal(np.asarray(values, theirs[key].dtype), theirs[key]):
            wrong.append(f"{key} differs")
    return wrong


def compare(work: Path, written: dict[str, object]) -> bool:
    from demonstrations import Demonstration, read_demo, read_demos

    ok = True
    for reading in sorted((work / "readings").glob("*.npz")):
        theirs = np.load(reading, allow_pickle=True)
        folder, _, stem = reading.stem.partition("-")
        if folder == "ours_dir":
            order = json.loads(str(theirs["files"]))
            parts = {
                p.name: d
                for p, d in zip(
                    sorted((work / "ours_dir").iterdir()),
                    read_demos(work / "ours_dir"),
                    strict=True,
                )
            }
            first = parts[order[0]]
            demo = Demonstration(
                first.meta,
                first.behavior_name,
                first.behavior_spec,
                tuple(s for f in order for s in parts[f].steps),
            )
            label = f"ours -> ML-Agents: directory of {len(order)} files"
        else:
            demo = read_demo(work / folder / f"{stem}.demo")
            direction = {"ours": "ours -> ML-Agents", "mlagents": "ML-Agents -> ours"}
            label = f"{direction.get(folder, 'Unity -> both')}: {stem}.demo"
        wrong = differences(demo, theirs)
        if folder == "ours":  # and ML-Agents read what we meant to write
            meant = written[stem]
            for a, b in zip(meant.steps, demo.steps, strict=True):
                for x, y in zip(a.observations, b.observations, strict=True):
                    if not np.allclose(x, y, rtol=0, atol=1e-7):
                        wrong.append("an observation is not what was written")
        sensors = [o.shape for o in demo.behavior_spec.observation_specs]
        a = demo.behavior_spec.action_spec
        print(
            f"{label}: {len(demo.steps)} steps, sensors {sensors}, actions "
            f"({a.continuous_size}, {list(a.discrete_branches)}): "
            + ("every field identical" if not wrong else "DIFFER: " + "; ".join(wrong[:5]))
        )
        ok &= not wrong
    return ok


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--real", type=Path, nargs="*", default=[], help="Unity-recorded files")
    parser.add_argument(
        "--anchor", type=Path, default=os.environ.get("MLAGENTS_ANCHOR", "/tmp/mlbench")
    )
    args = parser.parse_args()
    if not (args.anchor / "mlagents_learn_launcher.py").is_file():
        sys.exit(f"error: no mlagents-learn anchor in {args.anchor}: run the anchor recipe first")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        written = our_cases(work)
        (work / "real").mkdir()
        for file in args.real:
            shutil.copy(file, work / "real" / file.name)
        theirs = [str(args.anchor / "venv/bin/python"), str(SIDE), "--work", str(work)]
        env = {**os.environ, "PYTHONPATH": str(args.anchor / "shim")}
        command = [*theirs, "--anchor", str(args.anchor)]
        if subprocess.run(command, env=env, cwd=ROOT).returncode != 0:
            sys.exit("error: ML-Agents' side failed")
        ok = compare(work, written)
    print("agree" if ok else "DIFFER")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
