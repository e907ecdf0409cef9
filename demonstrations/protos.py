"""The protobuf side of a ``.demo`` file: ML-Agents' messages to our values and back.

Kept apart from the file layout (``demo_file``) so that each stays small: this module knows
what Unity puts in a ``BrainParametersProto`` and an ``ObservationProto`` (vector floats or
concatenated PNGs), ``demo_file`` knows where the messages lie. Problems are plain
:class:`ValueError` with a short text; ``demo_file`` adds the file name and the step.
"""

from __future__ import annotations

import io
import struct

import numpy as np
from mlagents_envs.base_env import (
    ActionSpec,
    BehaviorSpec,
    DimensionProperty,
    ObservationSpec,
    ObservationType,
)
from mlagents_envs.communicator_objects.agent_info_pb2 import AgentInfoProto
from mlagents_envs.communicator_objects.brain_parameters_pb2 import (
    ActionSpecProto,
    BrainParametersProto,
)
from mlagents_envs.communicator_objects.observation_pb2 import NONE, PNG, ObservationProto
from mlagents_envs.communicator_objects.space_type_pb2 import continuous, discrete
from PIL import Image

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def behavior_spec(brain: BrainParametersProto, first: AgentInfoProto) -> BehaviorSpec:
    """The spec as ML-Agents builds it: actions from the brain parameters (their deprecated
    fields in files from before the action spec existed), sensors from the first step."""
    sensors = []
    for obs in first.observations:
        try:
            kind = ObservationType(obs.observation_type)
        except ValueError:
            raise ValueError(f"unknown observation type {obs.observation_type}") from None
        dims = tuple(DimensionProperty(d) for d in obs.dimension_properties)
        sensors.append(
            ObservationSpec(
                shape=tuple(obs.shape),
                dimension_property=dims or (DimensionProperty.UNSPECIFIED,) * len(obs.shape),
                observation_type=kind,
                name=obs.name,
            )
        )
    spec = brain.action_spec
    if spec.num_continuous_actions or spec.num_discrete_actions:
        actions = ActionSpec(spec.num_continuous_actions, tuple(spec.discrete_branch_sizes))
    elif brain.vector_action_space_type_deprecated == continuous:
        sizes = brain.vector_action_size_deprecated
        if not sizes:
            raise ValueError("continuous actions of no size in the brain parameters")
        actions = ActionSpec(sizes[0], ())
    else:
        actions = ActionSpec(0, tuple(brain.vector_action_size_deprecated))
    return BehaviorSpec(sensors, actions)


def brain_parameters(behavior_name: str, actions: ActionSpec) -> BrainParametersProto:
    """What Unity's ``BrainParameters.ToProto(name, isTraining: false)`` writes: the action
    spec, and the deprecated fields synced from it as ``SyncDeprecatedActionFields`` does
    (sizes only when the actions are all of one kind; space type 0 = discrete otherwise)."""
    proto = BrainParametersProto(
        brain_name=behavior_name,
        is_training=False,
        action_spec=ActionSpecProto(
            num_continuous_actions=actions.continuous_size,
            num_discrete_actions=len(actions.discrete_branches),
            discrete_branch_sizes=actions.discrete_branches,
        ),
    )
    if actions.continuous_size == 0:
        proto.vector_action_size_deprecated.extend(actions.discrete_branches)
        proto.vector_action_space_type_deprecated = discrete
    elif not actions.discrete_branches:
        proto.vector_action_size_deprecated.append(actions.continuous_size)
        proto.vector_action_space_type_deprecated = continuous
    return proto


def observation_array(obs: ObservationProto) -> np.ndarray:
    """float32 in the observation's shape; PNGs decoded as ML-Agents decodes them."""
    shape = tuple(obs.shape)
    if obs.compression_type == NONE:
        data = np.array(obs.float_data.data, dtype=np.float32)
        if data.size != int(np.prod(shape)):
            raise ValueError(f"{data.size} floats cannot have shape {shape}")
        return data.reshape(shape)
    if obs.compression_type != PNG:
        raise ValueError(f"unknown compression type {obs.compression_type}")
    if len(shape) != 3:
        raise ValueError(f"a PNG observation of shape {shape} (PNGs are channels, height, width)")
    pixels = _decode_pngs(obs.compressed_data, shape[0], list(obs.compressed_channel_mapping))
    if pixels.shape != shape:
        raise ValueError(f"its PNGs decode to shape {pixels.shape}, the observation says {shape}")
    return pixels


def observation_proto(array: np.ndarray, sensor: ObservationSpec, png: bool) -> ObservationProto:
    """What Unity's ``GetObservationProto`` writes for one sensor: floats, or the channels as
    concatenated RGB PNGs with a channel mapping when there are more than three."""
    proto = ObservationProto(
        shape=sensor.shape,
        dimension_properties=[int(d) for d in sensor.dimension_property],
        observation_type=sensor.observation_type.value,
    )
    if sensor.name:
        proto.name = sensor.name
    if png:
        proto.compression_type = PNG
        proto.compressed_data, mapping = _encode_pngs(array)
        proto.compressed_channel_mapping.extend(mapping)
    else:
        proto.float_data.data.extend(np.asarray(array, np.float32).ravel().tolist())
    return proto


def _split_pngs(data: bytes) -> list[bytes]:
    """Concatenated PNG files, cut at each one's IEND chunk (a signature search could cut
    inside compressed data)."""
    images, start = [], 0
    while start < len(data):
        if data[start : start + 8] != PNG_SIGNATURE:
            raise ValueError(f"no PNG signature at byte {start} of the compressed data")
        pos = start + 8
        while True:
            if pos + 8 > len(data):
                raise ValueError("its compressed data ends inside a PNG")
            length, kind = struct.unpack(">I4s", data[pos : pos + 8])
            pos += 12 + length
            if kind == b"IEND":
                break
        if pos > len(data):
            raise ValueError("its compressed data ends inside a PNG")
        images.append(data[start:pos])
        start = pos
    return images


def _decode_pngs(data: bytes, channels: int, mapping: list[int]) -> np.ndarray:
    """Channels-first floats in [0, 1]: every PNG's channels in turn, then either averaged
    into the channels the mapping names (-1: padding) or, without a mapping, the first
    ``channels`` of them (one channel: the mean of the first image, Unity's greyscale)."""
    planes = []
    for png in _split_pngs(data):
        try:
            with Image.open(io.BytesIO(png)) as image:
                pixels = np.array(image, dtype=np.float32) / 255.0
        except (OSError, SyntaxError, ValueError) as error:
            raise ValueError(f"a PNG that does not decode ({error})") from None
        planes.append(pixels[np.newaxis] if pixels.ndim == 2 else np.moveaxis(pixels, -1, 0))
    if not planes:
        raise ValueError("a PNG observation without data")
    if mapping:
        stacked = np.concatenate(planes, axis=0)
        if len(mapping) != len(stacked) or sorted({m for m in mapping if m >= 0}) != list(
            range(max(mapping) + 1)
        ):
            raise ValueError(f"channel mapping {mapping} does not fit {len(stacked)} channels")
        merged = [
            np.mean(stacked[[i for i, m in enumerate(mapping) if m == c]], axis=0)
            for c in range(max(mapping) + 1)
        ]
        return np.stack(merged, axis=0)
    if channels == 1:
        return np.mean(planes[0], axis=0)[np.newaxis]
    return np.concatenate(planes, axis=0)[:channels]


def _encode_pngs(array: np.ndarray) -> tuple[bytes, list[int]]:
    """(channels, height, width) floats in [0, 1] as ceil(channels / 3) RGB PNGs (the last one
    padded with zeros), and the channel mapping Unity sends when there are more than three."""
    chw = np.asarray(array, np.float32)
    if chw.ndim != 3:
        raise ValueError(
            f"only (channels, height, width) observations can be PNGs, not {chw.shape}"
        )
    if not np.all((chw >= 0.0) & (chw <= 1.0)):
        raise ValueError("a PNG sensor with values outside [0, 1], which 8-bit pixels cannot hold")
    channels = chw.shape[0]
    if channels == 1:
        chw = np.repeat(chw, 3, axis=0)  # a greyscale camera: the same value in R, G and B
    padded = -(-chw.shape[0] // 3) * 3
    chw = np.concatenate([chw, np.zeros((padded - chw.shape[0], *chw.shape[1:]), np.float32)])
    pixels = np.rint(chw * 255.0).astype(np.uint8)
    out = io.BytesIO()
    for first in range(0, padded, 3):
        Image.fromarray(np.ascontiguousarray(np.moveaxis(pixels[first : first + 3], 0, -1))).save(
            out, format="PNG"
        )
    mapping = [*range(channels), *[-1] * (padded - channels)] if channels > 3 else []
    return out.getvalue(), mapping
