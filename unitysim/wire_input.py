"""Python's ``UnityMessageProto`` input read from its wire bytes, fast, for the player.

Why a module of its own: it is the other direction of :mod:`unitysim.wire` (which writes
the player's output) and shares nothing with it but the wire format. :func:`read_input` is
:func:`unitysim.messages.parse_input` of a message's bytes. Python's step inputs
(``mlagents_envs`` builds them, and so does our rollout) have one layout: every agent's
AgentActionProto the same size, with the deprecated vector, continuous and discrete fields
in that order. Such a behavior's actions are read as one numpy block; anything else (the
handshake, other layouts, malformed bytes) goes to protobuf.
``tests/unitysim/test_wire_input.py`` checks both read the same.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from unitysim.envs.base import Actions, Behavior
from unitysim.messages import Input, UnityMessageProto, parse_input


class _Unusual(Exception):
    """Bytes the fast reader does not take on: protobuf parses them instead."""


def read_input(data: bytes, behaviors: dict[str, Behavior]) -> Input:
    """:func:`unitysim.messages.parse_input` of ``data``, without protobuf for step inputs."""
    try:
        return _read_step(data, behaviors)
    except (_Unusual, IndexError, UnicodeDecodeError):  # (protobuf says what is wrong)
        return parse_input(UnityMessageProto.FromString(data), behaviors)


def _read_varint(data: bytes, pos: int) -> tuple[int, int]:
    byte = data[pos]
    if byte < 0x80:
        return byte, pos + 1
    value, shift = byte & 0x7F, 7
    while True:
        pos += 1
        byte = data[pos]
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos + 1
        shift += 7
        if shift > 63:
            raise _Unusual


def _read_fields(data: bytes, start: int, end: int) -> list[tuple[int, int, int]]:
    """The fields of one message: (tag, start, end) for length-delimited ones, (tag,
    value, -1) for varints; other wire types are left to protobuf."""
    fields, pos = [], start
    while pos < end:
        tag, pos = _read_varint(data, pos)
        if tag & 7 == 2:
            size, pos = _read_varint(data, pos)
            fields.append((tag, pos, pos + size))
            pos += size
        elif tag & 7 == 0:
            value, pos = _read_varint(data, pos)
            fields.append((tag, value, -1))
        else:
            raise _Unusual
    if pos != end:
        raise _Unusual
    return fields


def _int32(value: int) -> int:
    if value > 0x7FFFFFFF:  # negative (ten bytes on the wire) or out of range
        raise _Unusual
    return value


def _read_step(data: bytes, behaviors: dict[str, Behavior]) -> Input:
    status, rl_input = 0, None
    for tag, start, end in _read_fields(data, 0, len(data)):
        if tag == 0x0A:  # header (1): status (1), message (2)
            for field, value, _ in _read_fields(data, start, end):
                if field == 0x08:
                    status = _int32(value)
        elif tag == 0x1A:  # unity_input (3): rl_input (1); rl_initialization_input (2)
            for field, start2, end2 in _read_fields(data, start, end):
                if field != 0x0A or rl_input is not None:
                    raise _Unusual
                rl_input = (start2, end2)
        else:
            raise _Unusual
    command, side_channel, actions = 0, b"", {}
    if rl_input is not None:
        for tag, start, end in _read_fields(data, *rl_input):
            if tag == 0x0A:  # agent_actions (1): map entries of key (1), value (2)
                name, rows = "", (0, 0)
                for field, start2, end2 in _read_fields(data, start, end):
                    if field == 0x0A:
                        name = data[start2:end2].decode()
                    elif field == 0x12:
                        rows = (start2, end2)
                behavior = behaviors.get(name)
                if behavior is not None:
                    if name in actions:
                        raise _Unusual
                    actions[name] = _read_actions(data, *rows, behavior)
            elif tag == 0x20:  # command (4)
                command = _int32(start)
            elif tag == 0x2A:  # side_channel (5)
                side_channel = data[start:end]
            else:
                raise _Unusual
    return Input(status=status, command=command, actions=actions, side_channel=side_channel)


@dataclass(frozen=True)
class _ActionLayout:
    """An AgentActionProto (with its ListAgentActionProto.value tag and length) as
    mlagents_envs writes it: its size, its constant bytes, and where the values are."""

    width: int
    fixed: np.ndarray  # indices of the tag and length bytes
    expected: np.ndarray  # their values
    continuous: slice  # the continuous_actions float32s
    discrete: slice  # the discrete_actions varints (one byte each)


@functools.lru_cache(maxsize=256)
def _action_layout(continuous: int, branches: int) -> _ActionLayout | None:
    fields = (
        (0x0A, 4 * (continuous + branches)),  # vector_actions_deprecated (1): all, as floats
        (0x32, 4 * continuous),  # continuous_actions (6)
        (0x3A, branches),  # discrete_actions (7), values below 128
    )
    row, spans = [0x0A, 0], []
    for tag, size in fields:
        if size >= 128:
            return None
        spans.append(slice(len(row) + 2, len(row) + 2 + size))
        if size:
            row += [tag, size] + [-1] * size
    row[1] = len(row) - 2
    if row[1] >= 128:
        return None
    template = np.array(row)
    fixed = np.flatnonzero(template >= 0)
    return _ActionLayout(len(row), fixed, template[fixed].astype(np.uint8), spans[1], spans[2])


def _read_actions(data: bytes, start: int, end: int, behavior: Behavior) -> Actions:
    branches = len(behavior.branches)
    layout = _action_layout(behavior.continuous, branches)
    if layout is None or (end - start) % layout.width:
        raise _Unusual
    rows = np.frombuffer(data, np.uint8, end - start, start).reshape(-1, layout.width)
    if np.count_nonzero(rows[:, layout.fixed] != layout.expected):
        raise _Unusual
    discrete = rows[:, layout.discrete]
    if branches and np.count_nonzero(discrete >= 0x80):
        raise _Unusual
    continuous = rows[:, layout.continuous].copy().view("<f4")  # float32 (little-endian)
    return Actions(continuous, discrete.astype(np.int32))
