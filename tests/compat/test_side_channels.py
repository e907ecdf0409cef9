"""The side channels encode and decode with the wire layout of the protocol note."""

import struct
import uuid

import pytest
from mlagents_envs.side_channel import IncomingMessage, OutgoingMessage
from mlagents_envs.side_channel.engine_configuration_channel import (
    EngineConfig,
    EngineConfigurationChannel,
)
from mlagents_envs.side_channel.environment_parameters_channel import (
    EnvironmentParametersChannel,
)
from mlagents_envs.side_channel.side_channel_manager import SideChannelManager
from mlagents_envs.side_channel.stats_side_channel import (
    StatsAggregationMethod,
    StatsSideChannel,
)

ENGINE_ID = uuid.UUID("e951342c-4f7e-11ea-b238-784f4387d1f7")
PARAMS_ID = uuid.UUID("534c891e-810f-11ea-a9d0-822485860400")
STATS_ID = uuid.UUID("a1d8f7b7-cec8-50f9-b78b-d3e165a78520")


def split_records(blob: bytes) -> list[tuple[uuid.UUID, bytes]]:
    records, offset = [], 0
    while offset < len(blob):
        channel = uuid.UUID(bytes_le=bytes(blob[offset : offset + 16]))
        (length,) = struct.unpack_from("<i", blob, offset + 16)
        records.append((channel, bytes(blob[offset + 20 : offset + 20 + length])))
        offset += 20 + length
    return records


def test_channel_ids_on_the_wire():
    assert ENGINE_ID.bytes_le[:4] == bytes.fromhex("2c3451e9")
    assert EngineConfigurationChannel().channel_id == ENGINE_ID
    assert EnvironmentParametersChannel().channel_id == PARAMS_ID
    assert StatsSideChannel().channel_id == STATS_ID


def test_engine_configuration_encodes_one_record_per_setting():
    channel = EngineConfigurationChannel()
    channel.set_configuration(EngineConfig(84, 84, 3, 20.0, -1, 60))
    records = split_records(SideChannelManager([channel]).generate_side_channel_messages())
    assert {r[0] for r in records} == {ENGINE_ID}
    decoded = []
    for _, payload in records:
        message = IncomingMessage(payload)
        kind = message.read_int32()
        if kind == 0:
            decoded.append((kind, message.read_int32(), message.read_int32()))
        elif kind == 2:
            decoded.append((kind, message.read_float32()))
        else:
            decoded.append((kind, message.read_int32()))
    assert decoded == [(0, 84, 84), (1, 3), (2, 20.0), (3, -1), (4, 60)]
    # Sent once: the queue is cleared.
    assert SideChannelManager([channel]).generate_side_channel_messages() == b""


def test_environment_parameters_encode_values_and_samplers():
    channel = EnvironmentParametersChannel()
    channel.set_float_parameter("gravity", 4.5)
    channel.set_uniform_sampler_parameters("mass", 1.0, 2.0, 1234)
    channel.set_gaussian_sampler_parameters("scale", 1.0, 0.1, 7)
    channel.set_multirangeuniform_sampler_parameters("len", [(1.0, 2.0), (5.0, 6.0)], 9)
    records = split_records(SideChannelManager([channel]).generate_side_channel_messages())
    payloads = [payload for channel_id, payload in records if channel_id == PARAMS_ID]
    assert len(payloads) == 4

    gravity = IncomingMessage(payloads[0])
    assert (gravity.read_string(), gravity.read_int32()) == ("gravity", 0)
    assert gravity.read_float32() == 4.5
    # The exact bytes the protocol note recorded for the uniform sampler.
    key = b"mass"
    expected = (
        struct.pack("<i", len(key))
        + key
        + bytes.fromhex("01000000d2040000000000000000803f00000040")
    )
    assert payloads[1] == expected
    gaussian = IncomingMessage(payloads[2])
    assert gaussian.read_string() == "scale"
    assert [gaussian.read_int32() for _ in range(3)] == [1, 7, 1]
    assert gaussian.read_float32() == 1.0
    assert gaussian.read_float32() == pytest.approx(0.1)
    multi = IncomingMessage(payloads[3])
    assert multi.read_string() == "len"
    assert [multi.read_int32() for _ in range(3)] == [1, 9, 2]
    assert multi.read_float32_list() == [1.0, 2.0, 5.0, 6.0]


def test_stats_from_unity_decode():
    def record(key: str, value: float, method: int) -> bytes:
        message = OutgoingMessage()
        message.write_string(key)
        message.write_float32(value)
        message.write_int32(method)
        payload = bytes(message.buffer)
        return STATS_ID.bytes_le + struct.pack("<i", len(payload)) + payload

    stats = StatsSideChannel()
    blob = record("Ball/Height", 1.5, 0) + record("Ball/Height", 2.5, 0) + record("Goals", 3, 2)
    SideChannelManager([stats]).process_side_channel_message(blob)
    assert stats.get_and_reset_stats() == {
        "Ball/Height": [(1.5, StatsAggregationMethod.AVERAGE)] * 0
        + [(1.5, StatsAggregationMethod.AVERAGE), (2.5, StatsAggregationMethod.AVERAGE)],
        "Goals": [(3.0, StatsAggregationMethod.SUM)],
    }
    assert stats.get_and_reset_stats() == {}
