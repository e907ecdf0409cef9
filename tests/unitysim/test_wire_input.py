"""Python -> Unity input: ``messages.parse_input`` and the fast ``wire_input.read_input``.

``parse_input`` is the reference (protobuf objects); ``wire_input.read_input`` must read
the bytes of every input to the same ``Input``, on its fast path (the step inputs
``mlagents_envs`` sends) and through protobuf for everything else, errors included. Plain
unit tests: no processes, no gRPC. The behaviors are those of ``test_messages.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from google.protobuf.message import DecodeError
from mlagents_envs.communicator_objects.unity_message_pb2 import UnityMessageProto

from tests.unitysim.test_messages import CONTINUOUS, HYBRID, VECTOR
from unitysim import messages, wire_input
from unitysim.envs.base import Behavior

# --- parse_input -------------------------------------------------------------------------


def step_input(rows: dict[str, tuple[np.ndarray | None, np.ndarray | None]]) -> bytes:
    """A STEP input as mlagents_envs builds it (deprecated vector field filled too)."""
    message = UnityMessageProto()
    message.header.status = 200
    rl = message.unity_input.rl_input
    rl.command = messages.STEP
    rl.side_channel = b"side"
    for name, (continuous, discrete) in rows.items():
        n = len(continuous) if continuous is not None else len(discrete)
        for i in range(n):
            action = rl.agent_actions[name].value.add()
            if continuous is not None:
                action.vector_actions_deprecated.extend(continuous[i])
                action.continuous_actions.extend(continuous[i])
            if discrete is not None:
                action.vector_actions_deprecated.extend(discrete[i])
                action.discrete_actions.extend(discrete[i])
    return message.SerializeToString()


def test_parse_input_gathers_actions():
    rng = np.random.default_rng(10)
    continuous = rng.normal(size=(5, 1)).astype(np.float32)
    discrete = rng.integers(0, 3, (5, 2)).astype(np.int32)
    ball = rng.normal(size=(12, 2)).astype(np.float32)
    blob = step_input({HYBRID.name: (continuous, discrete), CONTINUOUS.name: (ball, None)})
    behaviors = {b.name: b for b in (HYBRID, CONTINUOUS)}
    parsed = messages.parse_input(UnityMessageProto.FromString(blob), behaviors)
    assert parsed.status == 200 and parsed.command == messages.STEP
    assert parsed.side_channel == b"side"
    hybrid = parsed.actions[HYBRID.name]
    np.testing.assert_array_equal(hybrid.continuous, continuous)
    np.testing.assert_array_equal(hybrid.discrete, discrete)
    assert hybrid.continuous.dtype == np.float32 and hybrid.discrete.dtype == np.int32
    assert parsed.actions[CONTINUOUS.name].discrete.shape == (12, 0)
    np.testing.assert_array_equal(parsed.actions[CONTINUOUS.name].continuous, ball)


def test_parse_input_ignores_unknown_behaviors_and_rejects_wrong_widths():
    blob = step_input({"Unknown?team=0": (np.zeros((2, 2), np.float32), None)})
    parsed = messages.parse_input(UnityMessageProto.FromString(blob), {})
    assert parsed.actions == {}
    blob = step_input({CONTINUOUS.name: (np.zeros((3, 3), np.float32), None)})
    with pytest.raises(ValueError):
        messages.parse_input(UnityMessageProto.FromString(blob), {CONTINUOUS.name: CONTINUOUS})


def test_parse_input_handshake_reply():
    message = UnityMessageProto()
    message.header.status = 200
    init = message.unity_input.rl_initialization_input
    init.seed, init.num_areas, init.communication_version = 42, 3, "1.5.0"
    parsed = messages.parse_input(message, {})
    assert (parsed.seed, parsed.num_areas, parsed.communication_version) == (42, 3, "1.5.0")


# --- wire_input.read_input: Python's bytes read without protobuf --------------------------

DISCRETE = Behavior("Discrete?team=0", (VECTOR,), branches=(3, 5, 2))
NO_ACTIONS = Behavior("Idle?team=0", (VECTOR,))


def assert_same_input(parsed: messages.Input, reference: messages.Input) -> None:
    assert (parsed.status, parsed.command, parsed.side_channel) == (
        reference.status,
        reference.command,
        reference.side_channel,
    )
    assert (parsed.seed, parsed.num_areas) == (reference.seed, reference.num_areas)
    assert parsed.actions.keys() == reference.actions.keys()
    for name, actions in parsed.actions.items():
        for got, want in zip(
            (actions.continuous, actions.discrete),
            (reference.actions[name].continuous, reference.actions[name].discrete),
            strict=True,
        ):
            assert got.dtype == want.dtype and got.shape == want.shape
            np.testing.assert_array_equal(got, want)


def test_read_input_takes_mlagents_step_inputs_without_protobuf():
    rng = np.random.default_rng(12)
    behaviors = {b.name: b for b in (CONTINUOUS, HYBRID, DISCRETE, NO_ACTIONS)}
    for n in (0, 1, 12, 40):
        ball = rng.normal(size=(n, 2)).astype(np.float32)
        ball[: n // 3, 0] = np.nan
        blob = step_input(
            {
                CONTINUOUS.name: (ball, None),
                HYBRID.name: (
                    rng.normal(size=(n, 1)).astype(np.float32),
                    rng.integers(0, 3, (n, 2)).astype(np.int32),
                ),
                DISCRETE.name: (None, rng.integers(0, 5, (n, 3)).astype(np.int32)),
                "Unknown?team=0": (ball, None),
            }
        )
        reference = messages.parse_input(UnityMessageProto.FromString(blob), behaviors)
        assert_same_input(wire_input._read_step(blob, behaviors), reference)  # the fast path
        assert_same_input(wire_input.read_input(blob, behaviors), reference)


def test_read_input_fast_path_takes_what_mlagents_itself_sends():
    """The layout the fast path expects, from mlagents_envs' own step-input builder."""
    from mlagents_envs.base_env import ActionTuple
    from mlagents_envs.environment import UnityEnvironment
    from mlagents_envs.side_channel.side_channel_manager import SideChannelManager

    rng = np.random.default_rng(13)
    env = object.__new__(UnityEnvironment)
    env._env_state = {CONTINUOUS.name: ([0] * 12, []), HYBRID.name: ([0] * 3, [])}
    env._side_channel_manager = SideChannelManager([])
    actions = {
        CONTINUOUS.name: ActionTuple(continuous=rng.normal(size=(12, 2)).astype(np.float32)),
        HYBRID.name: ActionTuple(
            continuous=rng.normal(size=(3, 1)).astype(np.float32),
            discrete=rng.integers(0, 2, size=(3, 2)).astype(np.int32),
        ),
    }
    message = UnityMessageProto()
    message.header.status = 200
    message.unity_input.CopyFrom(UnityEnvironment._generate_step_input(env, actions))
    blob = message.SerializeToString()
    behaviors = {b.name: b for b in (CONTINUOUS, HYBRID)}
    fast = wire_input._read_step(blob, behaviors)
    assert_same_input(fast, messages.parse_input(message, behaviors))
    np.testing.assert_array_equal(
        fast.actions[CONTINUOUS.name].continuous, actions[CONTINUOUS.name].continuous
    )


def test_read_input_leaves_other_messages_to_protobuf():
    behaviors = {b.name: b for b in (CONTINUOUS, DISCRETE)}
    handshake = UnityMessageProto()
    handshake.header.status = 200
    init = handshake.unity_input.rl_initialization_input
    init.seed, init.num_areas, init.communication_version = 42, 3, "1.5.0"
    lean = UnityMessageProto()  # continuous actions only: no deprecated vector
    lean.header.status = 200
    lean.unity_input.rl_input.agent_actions[CONTINUOUS.name].value.add(continuous_actions=[1, 2])
    wide = step_input({DISCRETE.name: (None, np.array([[1, 200, 3]], np.int32))})  # 2-byte varint
    closing = messages.status_message(400)
    for blob in (handshake.SerializeToString(), lean.SerializeToString(), wide):
        with pytest.raises(wire_input._Unusual):
            wire_input._read_step(blob, behaviors)
    for blob in (handshake.SerializeToString(), lean.SerializeToString(), wide, b""):
        reference = messages.parse_input(UnityMessageProto.FromString(blob), behaviors)
        assert_same_input(wire_input.read_input(blob, behaviors), reference)
    parsed = wire_input.read_input(closing.SerializeToString(), behaviors)
    assert parsed.status == 400 and parsed.actions == {}
    init_parsed = wire_input.read_input(handshake.SerializeToString(), {})
    assert (init_parsed.seed, init_parsed.communication_version) == (42, "1.5.0")


def test_read_input_errors_as_protobuf_does():
    blob = step_input({CONTINUOUS.name: (np.zeros((3, 3), np.float32), None)})  # 3 for 2
    with pytest.raises(ValueError):
        wire_input.read_input(blob, {CONTINUOUS.name: CONTINUOUS})
    good = step_input({CONTINUOUS.name: (np.zeros((3, 2), np.float32), None)})
    with pytest.raises(DecodeError):
        wire_input.read_input(good[:-3], {CONTINUOUS.name: CONTINUOUS})  # truncated
    named = step_input({"Ball?team=0": (np.zeros((1, 2), np.float32), None)})
    with pytest.raises(DecodeError):  # a behavior name that is not UTF-8
        wire_input.read_input(named.replace(b"Ball", b"B\xffll"), {CONTINUOUS.name: CONTINUOUS})
