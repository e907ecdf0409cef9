"""ML-Agents ``.demo`` files, read and written in the layout Unity's recorder produces.

The layout (Unity's ``DemonstrationWriter``, read by ``mlagents.trainers.demo_loader``):

* byte 0: ``DemonstrationMetaProto``, varint32-length-delimited. Unity writes it twice: a
  first one (the name) when recording starts, the final one over it when recording stops.
  Up to byte 33 (``MetaDataBytes`` = 32, plus one) the rest is zero padding.
* byte 33: the behavior's ``BrainParametersProto``, delimited.
* then one delimited ``AgentInfoActionPairProto`` per recorded step.
* then, in files Unity closed, a second, undelimited copy of the final metadata (its
  ``WriteMetadata`` writes the bytes at the end before seeking back to byte 0). Readers
  must stop after ``number_steps`` records; a file Unity never closed says 0 steps and
  holds records up to its end.

Everything wrong with a file is one :class:`DemoError` line naming it.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TypeVar

import numpy as np
from google.protobuf.message import DecodeError, Message
from mlagents_envs.base_env import BehaviorSpec
from mlagents_envs.communicator_objects.agent_action_pb2 import AgentActionProto
from mlagents_envs.communicator_objects.agent_info_action_pair_pb2 import (
    AgentInfoActionPairProto,
)
from mlagents_envs.communicator_objects.agent_info_pb2 import AgentInfoProto
from mlagents_envs.communicator_objects.brain_parameters_pb2 import BrainParametersProto
from mlagents_envs.communicator_objects.demonstration_meta_pb2 import DemonstrationMetaProto

from batches.specs import spec_mismatch
from demonstrations.protos import (
    behavior_spec,
    brain_parameters,
    observation_array,
    observation_proto,
)
from demonstrations.records import DemoError, DemoMeta, Demonstration, DemoStep

SUFFIX = ".demo"
META_AREA = 33  # where the brain parameters begin: Unity's MetaDataBytes (32) + 1
API_VERSION = 1  # Unity's DemonstrationMetaData.ApiVersion
READABLE_API_VERSIONS = frozenset({0, 1})  # what ML-Agents' demo_loader accepts

M = TypeVar("M", bound=Message)


def demo_files(path: str | os.PathLike[str]) -> list[Path]:
    """A ``.demo`` file, or every ``.demo`` file in a directory (by name: ML-Agents takes
    them in directory order, which no one can rely on)."""
    where = Path(path)
    if where.is_dir():
        found = sorted(p for p in where.iterdir() if p.name.endswith(SUFFIX) and p.is_file())
        if not found:
            raise DemoError(where, f"no {SUFFIX} files in this directory")
        return found
    if not where.exists():
        raise DemoError(where, "no such file or directory")
    if not where.name.endswith(SUFFIX):
        raise DemoError(where, f"not a {SUFFIX} file")
    return [where]


def read_demos(
    path: str | os.PathLike[str], expected: BehaviorSpec | None = None
) -> tuple[Demonstration, ...]:
    """Each file of :func:`demo_files`, checked against ``expected`` when given."""
    return tuple(_read_file(file, expected) for file in demo_files(path))


def read_demo(path: str | os.PathLike[str], expected: BehaviorSpec | None = None) -> Demonstration:
    """One file, or a directory's files as one demonstration (as ML-Agents trains on them):
    their steps in name order, their summaries added up under the directory's name (a
    directory of one file reads as that file).

    ``expected`` is the spec the caller's policy has: actions and sensor shapes must match
    it (what ML-Agents' ``demo_to_buffer`` checks). In a directory every file must match the
    first, which ML-Agents does not check.
    """
    demos = read_demos(path, expected)
    if len(demos) == 1:
        return demos[0]
    files = demo_files(path)
    first = demos[0]
    for file, demo in zip(files[1:], demos[1:], strict=True):
        if problem := spec_mismatch(demo.behavior_spec, first.behavior_spec):
            raise DemoError(file, f"{problem} (compared with {files[0].name})")
    episodes = sum(d.meta.episodes for d in demos)
    reward = sum(d.meta.mean_reward * d.meta.episodes for d in demos)
    meta = DemoMeta(
        Path(path).name,
        sum(d.meta.steps for d in demos),
        episodes,
        reward / episodes if episodes else 0.0,
    )
    steps = tuple(step for demo in demos for step in demo.steps)
    return Demonstration(meta, first.behavior_name, first.behavior_spec, steps)


def write_demo(path: str | os.PathLike[str], demo: Demonstration, png: Iterable[int] = ()) -> None:
    """Write ``demo`` byte for byte as Unity's recorder would (see the module's docstring).

    ``png``: indices of (channels, height, width) sensors to store as PNGs (values in [0, 1],
    quantized to 1/255) instead of floats. The summary's ``steps`` must count the steps
    (use :meth:`Demonstration.of_steps` to compute the summary).
    """
    where = Path(path)
    compressed = frozenset(png)
    spec = demo.behavior_spec
    try:
        _check_writable(demo, compressed)
        meta = _meta_proto(demo.meta).SerializeToString()
        if len(_varint(len(meta))) + len(meta) > META_AREA:
            raise ValueError(
                f"its metadata takes {len(meta)} bytes, more than a {SUFFIX} file has room for"
                f" before byte {META_AREA} (shorten the name)"
            )
        out = bytearray(_varint(len(meta)) + meta)
        out.extend(bytes(META_AREA - len(out)))
        _append(out, brain_parameters(demo.behavior_name, spec.action_spec))
        for index, step in enumerate(demo.steps):
            try:
                _append(out, _pair_proto(step, spec, compressed))
            except ValueError as error:
                raise ValueError(f"step {index}: {error}") from None
        out.extend(meta)  # Unity's undelimited copy at the end (see the module docstring)
    except ValueError as error:
        raise DemoError(where, str(error)) from None
    where.write_bytes(bytes(out))


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _append(out: bytearray, message: Message) -> None:
    body = message.SerializeToString()
    out.extend(_varint(len(body)))
    out.extend(body)


def _meta_proto(meta: DemoMeta) -> DemonstrationMetaProto:
    return DemonstrationMetaProto(
        api_version=API_VERSION,
        demonstration_name=meta.name,
        number_steps=meta.steps,
        number_episodes=meta.episodes,
        mean_reward=meta.mean_reward,
    )


def _check_writable(demo: Demonstration, png: frozenset[int]) -> None:
    """Refuse what ML-Agents could not read back: no steps (a file's sensors are only known
    from its first step), a summary that miscounts them, steps that break the spec."""
    spec = demo.behavior_spec
    if not demo.steps:
        raise ValueError("no steps to write: a file's sensors are known only from its steps")
    if demo.meta.steps != len(demo.steps):
        raise ValueError(f"its summary says {demo.meta.steps} steps, it has {len(demo.steps)}")
    sensors = spec.observation_specs
    if bad := sorted(i for i in png if not 0 <= i < len(sensors) or len(sensors[i].shape) != 3):
        raise ValueError(f"sensors {bad} cannot be PNGs: only (channels, height, width) ones can")
    actions = spec.action_spec
    wanted = [s.shape for s in sensors]
    for index, step in enumerate(demo.steps):
        if (shapes := [o.shape for o in step.observations]) != wanted:
            raise ValueError(f"step {index} has observation shapes {shapes}, the spec {wanted}")
        if step.continuous.size not in (0, actions.continuous_size):
            raise ValueError(f"step {index} has {step.continuous.size} continuous actions")
        if step.discrete.size not in (0, actions.discrete_size):
            raise ValueError(f"step {index} has {step.discrete.size} discrete actions")
        if step.action_mask.size not in (0, sum(actions.discrete_branches)):
            raise ValueError(f"step {index} has an action mask of {step.action_mask.size}")


def _pair_proto(step: DemoStep, spec: BehaviorSpec, png: frozenset[int]) -> Message:
    """What Unity's ``AgentInfo.ToInfoActionPairProto`` writes, the sensors added after."""
    info = AgentInfoProto(
        reward=step.reward,
        group_reward=step.group_reward,
        max_step_reached=step.interrupted,
        done=step.done,
        id=step.agent_id,
        group_id=step.group_id,
        action_mask=step.action_mask.tolist(),
    )
    for index, (array, sensor) in enumerate(
        zip(step.observations, spec.observation_specs, strict=True)
    ):
        info.observations.append(observation_proto(array, sensor, index in png))
    action = AgentActionProto(
        continuous_actions=step.continuous.tolist(), discrete_actions=step.discrete.tolist()
    )
    return AgentInfoActionPairProto(agent_info=info, action_info=action)


def _read_file(path: Path, expected: BehaviorSpec | None) -> Demonstration:
    try:
        data = path.read_bytes()
    except OSError as error:
        raise DemoError(path, f"cannot be read ({error.strerror or error})") from None
    try:
        demo = _parse(data)
    except ValueError as error:
        raise DemoError(path, str(error)) from None
    if expected is not None and (problem := spec_mismatch(demo.behavior_spec, expected)):
        raise DemoError(path, problem)
    return demo


def _parse(data: bytes) -> Demonstration:
    if not data:
        raise ValueError("empty file")
    meta, meta_end = _message(data, 0, DemonstrationMetaProto, "the metadata", limit=META_AREA)
    trailer = data[meta_end - meta.ByteSize() : meta_end]  # the copy a closed file ends with
    if meta.api_version not in READABLE_API_VERSIONS:
        raise ValueError(f"unsupported demonstration API version {meta.api_version}")
    if meta.number_steps < 0:
        raise ValueError(f"corrupt metadata ({meta.number_steps} steps)")
    brain, pos = _message(data, META_AREA, BrainParametersProto, "the brain parameters")
    pairs: list[AgentInfoActionPairProto] = []
    while len(pairs) < meta.number_steps or (
        meta.number_steps == 0 and pos < len(data) and data[pos:] != trailer
    ):
        if pos >= len(data):
            raise ValueError(
                f"truncated: its metadata says {meta.number_steps} steps, it ends after"
                f" {len(pairs)}"
            )
        pair, pos = _message(data, pos, AgentInfoActionPairProto, f"step {len(pairs)}")
        pairs.append(pair)
    if not pairs:
        raise ValueError("no steps, so no behavior spec (its sensors are known from steps only)")
    try:
        spec = behavior_spec(brain, pairs[0].agent_info)
    except ValueError as error:
        raise ValueError(f"corrupt behavior spec: {error}") from None
    steps = tuple(_step(i, pair, spec) for i, pair in enumerate(pairs))
    # a file Unity never closed says 0 steps: the summary counts what it holds
    summary = DemoMeta(meta.demonstration_name, len(steps), meta.number_episodes, meta.mean_reward)
    return Demonstration(summary, brain.brain_name, spec, steps)


def _message(
    data: bytes, pos: int, kind: Callable[[], M], what: str, limit: int | None = None
) -> tuple[M, int]:
    """The delimited message at ``pos`` and where the next one begins."""
    size, start = _read_varint(data, pos, what)
    end = start + size
    if end > len(data):
        raise ValueError(
            f"truncated: {what} at byte {pos} needs {size} bytes, {len(data) - start} left"
        )
    if limit is not None and end > limit:
        raise ValueError(f"corrupt: {what} runs past byte {limit} ({size} bytes)")
    message = kind()
    try:
        message.ParseFromString(data[start:end])
    except DecodeError:
        raise ValueError(f"corrupt: {what} at byte {pos} does not decode") from None
    return message, end


def _read_varint(data: bytes, pos: int, what: str) -> tuple[int, int]:
    """A protobuf varint32 length (up to five bytes) and where it ends."""
    value = 0
    for shift, index in enumerate(range(pos, min(pos + 5, len(data)))):
        value |= (data[index] & 0x7F) << (7 * shift)
        if not data[index] & 0x80:
            return value & 0xFFFFFFFF, index + 1
    if pos + 5 > len(data):
        raise ValueError(f"truncated: the file ends at byte {len(data)}, before {what}")
    raise ValueError(f"corrupt: the length of {what} at byte {pos} is not a varint")


def _step(index: int, pair: AgentInfoActionPairProto, spec: BehaviorSpec) -> DemoStep:
    info, action = pair.agent_info, pair.action_info
    sensors = spec.observation_specs
    if len(info.observations) != len(sensors):
        raise ValueError(
            f"step {index} has {len(info.observations)} observations, the first step {len(sensors)}"
        )
    observations = []
    for i, (obs, sensor) in enumerate(zip(info.observations, sensors, strict=True)):
        if tuple(obs.shape) != sensor.shape:
            raise ValueError(
                f"step {index}: observation {i} has shape {tuple(obs.shape)}, "
                f"the first step's {sensor.shape}"
            )
        try:
            observations.append(observation_array(obs))
        except ValueError as error:
            raise ValueError(f"step {index}: observation {i}: {error}") from None
    continuous, discrete = _actions_of(action, spec)
    return DemoStep(
        observations=tuple(observations),
        reward=info.reward,
        done=info.done,
        interrupted=info.max_step_reached,
        agent_id=info.id,
        action_mask=np.array(info.action_mask, dtype=bool),
        continuous=continuous,
        discrete=discrete,
        group_id=info.group_id,
        group_reward=info.group_reward,
    )


def _actions_of(
    action: AgentActionProto, spec: BehaviorSpec
) -> tuple[Sequence[float], Sequence[int]]:
    """Files from before hybrid actions keep them in ``vector_actions_deprecated``: ML-Agents
    reads those as continuous when the spec has continuous actions, else as discrete."""
    if action.continuous_actions or action.discrete_actions:
        return list(action.continuous_actions), list(action.discrete_actions)
    old = list(action.vector_actions_deprecated)
    if spec.action_spec.continuous_size > 0:
        return old, []
    return [], [int(a) for a in old]
