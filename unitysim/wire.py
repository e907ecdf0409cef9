"""The player's ``UnityMessageProto`` output wire bytes, written directly, fast.

:func:`unitysim.messages.rl_output` builds the per-step output (U3...) as protobuf objects,
field by field: the reference, plain to read and obviously right, but at several µs per
agent it made the stand-in, rather than the trainer, limit a raw ``UnityEnvironment``
loop. :func:`encode_rl_output` writes the same message's bytes (proto3: defaults omitted,
repeated scalars packed, fields in number order). What is the same for every agent of a
sensor (shape, dimension properties, type, name, lengths) is encoded once per sensor; the
float observations of all agents are laid out in one numpy array; per agent only a few
byte strings are joined. ``tests/unitysim/test_messages.py`` checks that both parse to
equal messages.

:func:`encode_output` is what the player uses (``UNITYSIM_REFERENCE_ENCODER=1`` at player
start selects the reference, so benchmarks compare both in one run); :func:`to_bytes` is
its gRPC request serializer. Python's input bytes are read the same way, without protobuf,
in :mod:`unitysim.wire_input`.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from unitysim.envs.base import AgentInfos, Behavior, Sensor
from unitysim.messages import UnityMessageProto, brain_parameters, rl_output
from unitysim.png import encode_batch as encode_png_batch

REFERENCE_ENCODER_VARIABLE = "UNITYSIM_REFERENCE_ENCODER"
_Key = TypeVar("_Key")
_Value = TypeVar("_Value")

#
# Tags are (field number << 3) | wire type; wire types: 0 varint, 2 length-delimited,
# 5 fixed 32-bit. Message and field names below are those of unity-protocol.md §3.

_ONE_BYTE = tuple(bytes((value,)) for value in range(128))
_NO_FLOAT = b"\0\0\0\0"
_HEADER_200 = b"\x0a\x03\x08\xc8\x01"  # header { status: 200 }
# AgentInfoProto: reward 7 (fixed32), done 8, max_step_reached 9, id 10 (varints),
# action_mask 11 (packed), observations 13, group_id 14 (varint), group_reward 15 (fixed32)
_REWARD, _ID, _MASK, _OBSERVATION, _GROUP_ID, _GROUP_REWARD = b"=", b"P", b"Z", b"j", b"p", b"}"
_FLAGS = (b"", b"\x48\x01", b"\x40\x01", b"\x40\x01\x48\x01")  # by done * 2 + max_step
_VALUE = b"\x0a"  # ListAgentInfoProto.value (1), and map keys (1)
_MAP_ENTRY, _MAP_VALUE = b"\x12", b"\x12"  # UnityRLOutputProto.agentInfos (2); entry value (2)


def _varint(value: int) -> bytes:
    """A protobuf varint; negative int32 values take ten bytes, as protobuf writes them."""
    if 0 <= value < 128:
        return _ONE_BYTE[value]
    value &= (1 << 64) - 1
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _field(tag: bytes, payload: bytes) -> bytes:
    """A length-delimited field."""
    return tag + _varint(len(payload)) + payload


def _packed(tag: bytes, values: Sequence[int]) -> bytes:
    """A packed repeated varint field; nothing when empty (the proto3 default)."""
    return _field(tag, b"".join(_varint(int(v)) for v in values)) if len(values) else b""


def _cached(function: Callable[[_Key], _Value]) -> Callable[[_Key], _Value]:
    """``functools.lru_cache``, except that unhashable arguments (a Sensor built with lists
    instead of tuples, say) are computed afresh instead of failing."""
    cached = functools.lru_cache(maxsize=256)(function)

    @functools.wraps(function)
    def call(key: _Key) -> _Value:
        try:
            return cached(key)
        except TypeError:
            try:
                hash(key)
            except TypeError:
                return function(key)
            raise

    return call


@functools.lru_cache(maxsize=8192)
def _id_field(agent_id: int) -> bytes:
    return _ID + _varint(agent_id) if agent_id else b""


@dataclass(frozen=True)
class _SensorCodec:
    """What one sensor's ObservationProto looks like around its data, encoded once.

    Float sensors: ``head`` + the row's little-endian float32s + ``tail`` is the whole
    ``observations`` field of an agent (tag and length included: every row has the same
    size). PNG sensors: ``head`` + ``compressed_data`` field + ``tail`` is the message body.
    """

    head: bytes
    tail: bytes
    size: int  # floats per row
    png: bool


@_cached
def _codec(sensor: Sensor) -> _SensorCodec:
    shape = _packed(b"\x0a", sensor.shape)  # shape (1)
    tail = (
        _packed(b"\x32", sensor.dimension_properties)  # dimension_properties (6)
        + (b"\x38" + _varint(sensor.observation_type) if sensor.observation_type else b"")  # (7)
        + (_field(b"\x42", sensor.name.encode()) if sensor.name else b"")  # name (8)
    )
    size = int(np.prod(sensor.shape))
    if sensor.png:
        return _SensorCodec(shape + b"\x10\x01", tail, size, png=True)  # compression_type PNG
    floats = 4 * size
    float_data = b"\x0a" + _varint(floats) if floats else b""  # FloatData.data (1), packed
    before = shape + b"\x22" + _varint(len(float_data) + floats) + float_data  # float_data (4)
    body = len(before) + floats + len(tail)
    return _SensorCodec(_OBSERVATION + _varint(body) + before, tail, size, png=False)


@_cached
def _sensor_codecs(behavior: Behavior) -> tuple[_SensorCodec, ...]:
    return tuple(_codec(sensor) for sensor in behavior.sensors)


@functools.lru_cache(maxsize=256)
def _float_layout(sensors: tuple[_SensorCodec, ...]) -> tuple[np.ndarray, tuple[slice, ...]]:
    """The ``observations`` fields of float sensors for one agent as a template row (the
    constant bytes in place) and, per sensor, where its float32s go in that row."""
    row, spans = bytearray(), []
    for codec in sensors:
        row += codec.head
        spans.append(slice(len(row), len(row) + 4 * codec.size))
        row += bytes(4 * codec.size) + codec.tail
    return np.frombuffer(bytes(row), dtype=np.uint8), tuple(spans)


def _float_rows(
    sensors: tuple[_SensorCodec, ...], batches: Sequence[np.ndarray], n: int
) -> list[bytes]:
    """Per agent, the ``observations`` fields of float sensors: the template row with the
    agent's little-endian float32s written in (all agents in one array)."""
    template, spans = _float_layout(sensors)
    width = len(template)
    if width == 0:
        return [b""] * n
    block = np.empty((n, width), dtype=np.uint8)
    block[:] = template
    for span, batch in zip(spans, batches, strict=True):
        if span.stop > span.start:  # (unaligned float32 views are fine for numpy)
            block[:, span].view("<f4")[...] = batch.reshape(n, (span.stop - span.start) // 4)
    raw = block.tobytes()
    return [raw[i : i + width] for i in range(0, n * width, width)]


def _observation_fields(behavior: Behavior, obs: Sequence[np.ndarray], n: int) -> list[bytes]:
    """Per agent, all its ``observations`` fields, in sensor order."""
    sensors = _sensor_codecs(behavior)
    if len(sensors) != len(obs):
        raise ValueError(f"{behavior.name}: {len(obs)} observations for {len(sensors)} sensors")
    if not any(sensor.png for sensor in sensors):
        return _float_rows(sensors, obs, n)
    per_sensor = [
        [
            _field(_OBSERVATION, sensor.head + _field(b"\x1a", png) + sensor.tail)
            for png in encode_png_batch(batch)
        ]
        if sensor.png
        else _float_rows((sensor,), [batch], n)
        for sensor, batch in zip(sensors, obs, strict=True)
    ]
    return [b"".join(fields) for fields in zip(*per_sensor, strict=True)]


def _float_fields(tag: bytes, values: np.ndarray) -> list[bytes]:
    """A float32 field per agent: tag and four bytes, or nothing for +0.0 (proto3)."""
    raw = np.ascontiguousarray(values, dtype="<f4").tobytes()
    return [
        tag + raw[i : i + 4] if raw[i : i + 4] != _NO_FLOAT else b"" for i in range(0, len(raw), 4)
    ]


def _any_bits(values: np.ndarray) -> bool:
    """Whether any float32 differs from +0.0 (a -0.0 is written, as protobuf does)."""
    return bool(np.count_nonzero(np.ascontiguousarray(values, dtype="<f4").view("<u4")))


def _agent_infos(behavior: Behavior, infos: AgentInfos) -> bytes:
    """The ``value`` fields of one ListAgentInfoProto (the agents' AgentInfoProtos)."""
    n = len(infos)
    if n == 0:
        return b""
    observations = _observation_fields(behavior, infos.obs, n)
    rewards = _float_fields(_REWARD, infos.reward)
    if np.count_nonzero(infos.done) or np.count_nonzero(infos.max_step_reached):
        flags = [
            _FLAGS[f] for f in (2 * infos.done.astype(np.int8) + infos.max_step_reached).tolist()
        ]
    else:
        flags = [b""] * n
    ids = [_id_field(agent_id) for agent_id in infos.agent_id.tolist()]
    mask = infos.action_mask
    if mask is not None and behavior.branches and mask.size:
        mask = np.ascontiguousarray(mask, dtype=np.bool_).reshape(n, -1)
        prefix, width, raw = _MASK + _varint(mask.shape[1]), mask.shape[1], mask.tobytes()
        masks = [prefix + raw[i : i + width] for i in range(0, n * width, width)]
    else:
        masks = [b""] * n
    if np.count_nonzero(infos.group_id) or _any_bits(infos.group_reward):
        group_ids = [_GROUP_ID + _varint(g) if g else b"" for g in infos.group_id.tolist()]
        group_rewards = _float_fields(_GROUP_REWARD, infos.group_reward)
        groups = [a + b for a, b in zip(group_ids, group_rewards, strict=True)]
    else:
        groups = [b""] * n
    records = []
    for fields in zip(rewards, flags, ids, masks, observations, groups, strict=True):
        body = b"".join(fields)
        records += (_VALUE, _varint(len(body)), body)
    return b"".join(records)


@_cached
def _brain_parameters_field(behavior: Behavior) -> bytes:
    """UnityRLInitializationOutputProto.brain_parameters (5) for one behavior."""
    return _field(b"\x2a", brain_parameters(behavior).SerializeToString())


def encode_rl_output(
    behaviors: dict[str, Behavior],
    output: dict[str, AgentInfos],
    announce: list[Behavior],
    side_channel: bytes = b"",
) -> bytes:
    """:func:`rl_output`, serialized, but written directly (see the module docstring)."""
    entries = []
    for name, infos in output.items():
        key = _field(_VALUE, name.encode())
        entries.append(
            _field(_MAP_ENTRY, key + _field(_MAP_VALUE, _agent_infos(behaviors[name], infos)))
        )
    if side_channel:
        entries.append(_field(b"\x1a", bytes(side_channel)))  # side_channel (3)
    unity_output = _field(b"\x0a", b"".join(entries))  # rl_output (1), always present
    if announce:
        init = b"".join(_brain_parameters_field(b) for b in announce)
        unity_output += _field(b"\x12", init)  # rl_initialization_output (2)
    return _HEADER_200 + _field(b"\x12", unity_output)  # unity_output (2)


def reference_rl_output(
    behaviors: dict[str, Behavior],
    output: dict[str, AgentInfos],
    announce: list[Behavior],
    side_channel: bytes = b"",
) -> bytes:
    """The reference encoder's bytes (:func:`rl_output`, serialized by protobuf)."""
    return rl_output(behaviors, output, announce, side_channel).SerializeToString()


_USE_REFERENCE = os.environ.get(REFERENCE_ENCODER_VARIABLE, "") not in ("", "0")

#: What the player sends each step: the fast encoder, or the reference one where
#: ``UNITYSIM_REFERENCE_ENCODER=1`` was set when the player started (benchmarks).
encode_output: Callable[..., bytes] = reference_rl_output if _USE_REFERENCE else encode_rl_output


def to_bytes(message: UnityMessageProto | bytes) -> bytes:
    """The player's gRPC request serializer: bytes pass through, messages are serialized."""
    return message if isinstance(message, bytes) else message.SerializeToString()
