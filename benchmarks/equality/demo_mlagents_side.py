"""ML-Agents' side of ``check_demo_vs_mlagents.py``, run in the anchor recipe's venv as a
plain file (by its path, not ``-m``): it imports nothing of ours, only the standard
library, numpy and ML-Agents, and ``check_demo_vs_mlagents.py`` imports its ``FIELDS``.

It writes ``.demo`` files with ML-Agents' Python ``write_demo`` (records filled as Unity's
C# ``GrpcExtensions`` fills them) and reads every file it is given with ML-Agents'
``demo_loader``, saving what it read as ``.npz`` files for the comparison.

    /tmp/mlbench/venv/bin/python benchmarks/equality/demo_mlagents_side.py --work DIR \\
        --anchor /tmp/mlbench
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

FIELDS = ("reward", "done", "max_step", "agent_id", "group_id", "group_reward")


def anchor_workarounds(anchor: Path) -> None:
    """The anchor launcher's runtime workarounds, before ML-Agents is imported."""
    preamble = (anchor / "mlagents_learn_launcher.py").read_text()
    preamble = preamble.split("from mlagents.trainers.learn import main")[0]
    exec(compile(preamble, "mlagents_learn_launcher.py", "exec"), {})


def mlagents_writes(out: Path) -> None:
    """Files written with ML-Agents' Python ``write_demo``, records filled as Unity does."""
    import io

    from mlagents.trainers.demo_loader import write_demo
    from mlagents_envs.communicator_objects.agent_action_pb2 import AgentActionProto
    from mlagents_envs.communicator_objects.agent_info_action_pair_pb2 import (
        AgentInfoActionPairProto,
    )
    from mlagents_envs.communicator_objects.agent_info_pb2 import AgentInfoProto
    from mlagents_envs.communicator_objects.brain_parameters_pb2 import (
        ActionSpecProto,
        BrainParametersProto,
    )
    from mlagents_envs.communicator_objects.demonstration_meta_pb2 import (
        DemonstrationMetaProto,
    )
    from mlagents_envs.communicator_objects.observation_pb2 import ObservationProto
    from PIL import Image

    def png(chw: np.ndarray) -> bytes:
        planes = np.concatenate([chw, np.zeros((-len(chw) % 3, *chw.shape[1:]), np.uint8)])
        if len(chw) == 1:
            planes = np.repeat(chw, 3, axis=0)  # a greyscale camera: R = G = B
        data = b""
        for first in range(0, len(planes), 3):
            buffer = io.BytesIO()
            Image.fromarray(planes[first : first + 3].transpose(1, 2, 0).copy()).save(buffer, "PNG")
            data += buffer.getvalue()
        return data

    def observation(kind: str, shape: tuple[int, ...], name: str, rng) -> ObservationProto:
        proto = ObservationProto(
            shape=shape, name=name, dimension_properties=[1, 2, 2][: len(shape)]
        )
        if kind == "png":
            proto.compression_type = 1
            proto.compressed_data = png(rng.integers(0, 256, shape, dtype=np.uint8))
            if shape[0] > 3:
                proto.compressed_channel_mapping.extend([*range(shape[0]), *[-1] * (-shape[0] % 3)])
        else:
            proto.float_data.data.extend(rng.normal(size=shape).astype(np.float32).ravel())
        return proto

    cases = {  # name: (continuous, branches, sensors, legacy, Unity's trailing copy)
        "ml_discrete": (0, (3, 2), [("vec", (8,)), ("vec", (3,))], False, True),
        "ml_continuous": (2, (), [("vec", (6,))], False, False),
        "ml_visual": (
            1,
            (2,),
            [("png", (3, 8, 8)), ("png", (5, 4, 4)), ("png", (1, 6, 6)), ("vec", (4,))],
            False,
            True,
        ),
        "ml_legacy": (2, (), [("vec", (3,))], True, True),
    }
    for seed, (name, (continuous, branches, sensors, legacy, trailer)) in enumerate(cases.items()):
        rng = np.random.default_rng(seed)
        brain = BrainParametersProto(brain_name=f"{name}?team=0")
        if not legacy:
            brain.action_spec.CopyFrom(
                ActionSpecProto(
                    num_continuous_actions=continuous,
                    num_discrete_actions=len(branches),
                    discrete_branch_sizes=branches,
                )
            )
        if not continuous or not branches:
            brain.vector_action_size_deprecated.extend(branches or (continuous,))
            brain.vector_action_space_type_deprecated = 1 if continuous else 0
        pairs, total, dones = [], np.float32(0), 0
        for i in range(11):
            done = i % 4 == 3
            info = AgentInfoProto(
                reward=rng.normal(),
                done=done,
                max_step_reached=done and i == 7,
                id=3 + i // 4,
                group_id=i % 2,
                group_reward=rng.normal(),
                action_mask=(rng.random(sum(branches)) < 0.3).tolist() if i % 3 else [],
            )
            for k, (kind, shape) in enumerate(sensors):
                info.observations.append(observation(kind, shape, f"{kind}{k}", rng))
            action = AgentActionProto()
            values = rng.normal(size=continuous).astype(np.float32).tolist()
            if legacy:
                action.vector_actions_deprecated.extend(values)
            else:
                action.continuous_actions.extend(values)
                action.discrete_actions.extend(int(rng.integers(0, b)) for b in branches)
            pairs.append(AgentInfoActionPairProto(agent_info=info, action_info=action))
            total, dones = np.float32(total + np.float32(info.reward)), dones + done
        meta = DemonstrationMetaProto(
            api_version=0 if legacy else 1,
            demonstration_name=name[:16],
            number_steps=11,
            number_episodes=dones + 1,
            mean_reward=float(total / np.float32(dones + 1)),
        )
        path = out / f"{name}.demo"
        write_demo(str(path), meta, brain, pairs)
        if trailer:
            with path.open("ab") as f:
                f.write(meta.SerializeToString())


def mlagents_reads(path: Path, out: Path) -> None:
    """What ML-Agents' loader reads from ``path`` (a file or a directory), as an ``.npz``."""
    from google.protobuf.internal.decoder import _DecodeVarint32
    from mlagents.trainers.buffer import BufferKey
    from mlagents.trainers.demo_loader import demo_to_buffer, get_demo_files, load_demonstration
    from mlagents.trainers.trajectory import ObsUtil
    from mlagents_envs.communicator_objects.demonstration_meta_pb2 import (
        DemonstrationMetaProto,
    )
    from mlagents_envs.rpc_utils import steps_from_proto

    spec, pairs, total = load_demonstration(str(path))
    _, buffer = demo_to_buffer(str(path), 1, spec)
    actions = spec.action_spec
    found: dict[str, np.ndarray] = {}
    sensors = [
        {
            "shape": list(o.shape),
            "dims": [int(d) for d in o.dimension_property],
            "type": o.observation_type.value,
            "name": o.name,
        }
        for o in spec.observation_specs
    ]
    spec_json = {
        "sensors": sensors,
        "continuous": actions.continuous_size,
        "branches": list(actions.discrete_branches),
    }
    found["spec"] = np.array(json.dumps(spec_json))
    found["files"] = np.array(json.dumps([Path(f).name for f in get_demo_files(str(path))]))
    if path.is_file():
        data = path.read_bytes()
        size, pos = _DecodeVarint32(data, 0)
        meta = DemonstrationMetaProto.FromString(data[pos : pos + size])
        found["meta"] = np.array(
            json.dumps(
                [meta.demonstration_name, meta.number_steps, meta.number_episodes, meta.mean_reward]
            )
        )
    infos = [p.agent_info for p in pairs]
    for name, attr in zip(
        FIELDS,
        ("reward", "done", "max_step_reached", "id", "group_id", "group_reward"),
        strict=True,
    ):
        found[name] = np.array([getattr(i, attr) for i in infos])
    for i in range(len(sensors)):  # decoded as make_demo_buffer decodes them
        rows = []
        for info in infos:
            decision, terminal = steps_from_proto([info], spec)
            rows.append((terminal if info.done else decision).obs[i][0])
        found[f"obs_{i}"] = np.stack(rows)
    found["mask"] = np.array([list(i.action_mask) for i in infos], dtype=object)
    continuous, discrete = [], []
    for p in pairs:  # as make_demo_buffer picks them
        a = p.action_info
        if not a.continuous_actions and not a.discrete_actions:
            old = list(a.vector_actions_deprecated)
            continuous.append(old if actions.continuous_size else [])
            discrete.append([] if actions.continuous_size else old)
        else:
            continuous.append(list(a.continuous_actions))
            discrete.append(list(a.discrete_actions))
    found["continuous"] = np.array(continuous, dtype=object)
    found["discrete"] = np.array(discrete, dtype=object)
    found["buffer_done"] = np.array(buffer[BufferKey.DONE], dtype=bool)
    found["buffer_reward"] = np.array(buffer[BufferKey.ENVIRONMENT_REWARDS], np.float32)
    for i in range(len(sensors)):
        found[f"buffer_obs_{i}"] = np.array(buffer[ObsUtil.get_name_at(i)], np.float32)
    if actions.continuous_size:
        found["buffer_continuous"] = np.array(buffer[BufferKey.CONTINUOUS_ACTION], np.float32)
    if actions.discrete_size:
        found["buffer_discrete"] = np.array(buffer[BufferKey.DISCRETE_ACTION], np.float32)
    np.savez(out, total=total, **found)


def mlagents_side(work: Path, anchor: Path) -> None:
    """Write ML-Agents' cases into ``work/mlagents``, then read every case (ours, its own,
    the real recordings, our directory) into ``work/readings``."""
    anchor_workarounds(anchor)
    (work / "mlagents").mkdir()
    mlagents_writes(work / "mlagents")
    (work / "readings").mkdir()
    for folder in ("ours", "mlagents", "real"):
        for path in sorted((work / folder).glob("*.demo")):
            mlagents_reads(path, work / "readings" / f"{folder}-{path.stem}.npz")
    mlagents_reads(work / "ours_dir", work / "readings" / "ours_dir.npz")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--anchor", type=Path, required=True)
    args = parser.parse_args()
    mlagents_side(args.work, args.anchor)
