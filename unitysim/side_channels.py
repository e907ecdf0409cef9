"""Unity's side of the side channels: read what Python sends, write what Unity sends.

Framing (both directions): 16-byte channel id (``uuid.bytes_le``), int32 length, payload;
payload primitives are little-endian. Python -> Unity: engine configuration, environment
parameters (values and seeded samplers) and training analytics (ignored, as real builds
without the analytics module do). Unity -> Python: stats. Messages for channels this
player does not know are kept, as real Unity caches them for channels registered later.
"""

from __future__ import annotations

import logging
import struct
import uuid
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from unitysim.envs.base import Parameters, Sampler, StatsMethod

ENGINE_CONFIGURATION = uuid.UUID("e951342c-4f7e-11ea-b238-784f4387d1f7")
ENVIRONMENT_PARAMETERS = uuid.UUID("534c891e-810f-11ea-a9d0-822485860400")
STATS = uuid.UUID("a1d8f7b7-cec8-50f9-b78b-d3e165a78520")
TRAINING_ANALYTICS = uuid.UUID("b664a4a9-d86f-5a5f-95cb-e8353a7e8356")

log = logging.getLogger("unitysim")


class SideChannelError(ValueError):
    """Malformed side-channel bytes from Python."""


def split_records(blob: bytes) -> list[tuple[uuid.UUID, bytes]]:
    records, offset = [], 0
    while offset < len(blob):
        if offset + 20 > len(blob):
            raise SideChannelError("side-channel record header is truncated")
        channel = uuid.UUID(bytes_le=bytes(blob[offset : offset + 16]))
        (length,) = struct.unpack_from("<i", blob, offset + 16)
        end = offset + 20 + length
        if length < 0 or end > len(blob):
            raise SideChannelError(f"side-channel record for {channel} is truncated")
        records.append((channel, bytes(blob[offset + 20 : end])))
        offset = end
    return records


def frame(channel: uuid.UUID, payload: bytes) -> bytes:
    return channel.bytes_le + struct.pack("<i", len(payload)) + payload


class Reader:
    """Reads payload primitives; past the end it yields defaults, as the C# reader does."""

    def __init__(self, payload: bytes) -> None:
        self._data = payload
        self._offset = 0

    def _unpack(self, fmt: str, default: float | int) -> float | int:
        size = struct.calcsize(fmt)
        if self._offset + size > len(self._data):
            self._offset = len(self._data)
            return default
        (value,) = struct.unpack_from(fmt, self._data, self._offset)
        self._offset += size
        return value

    def int32(self) -> int:
        return int(self._unpack("<i", 0))

    def float32(self) -> float:
        return float(self._unpack("<f", 0.0))

    def string(self) -> str:
        length = self.int32()
        raw = self._data[self._offset : self._offset + length]
        self._offset += len(raw)
        return raw.decode("ascii", errors="replace")

    def float_list(self) -> list[float]:
        return [self.float32() for _ in range(self.int32())]


def write_string(text: str) -> bytes:
    raw = text.encode("ascii", errors="replace")
    return struct.pack("<i", len(raw)) + raw


@dataclass
class EngineSettings:
    """What the EngineConfiguration channel set; a headless player only records it."""

    width: int = 80
    height: int = 80
    quality_level: int = 1
    time_scale: float = 1.0
    target_frame_rate: int = -1
    capture_frame_rate: int = 60


def _sampler(sampler_type: int, seed: int, reader: Reader) -> Sampler | None:
    rng = np.random.default_rng(seed)
    if sampler_type == 0:
        low, high = reader.float32(), reader.float32()
        return lambda: float(rng.uniform(low, high))
    if sampler_type == 1:
        mean, std = reader.float32(), reader.float32()
        return lambda: float(rng.normal(mean, std))
    if sampler_type == 2:
        bounds = reader.float_list()
        intervals = np.array(bounds, dtype=np.float64).reshape(-1, 2)
        widths = intervals[:, 1] - intervals[:, 0]
        weights = widths / widths.sum()

        def draw() -> float:
            low, high = intervals[rng.choice(len(intervals), p=weights)]
            return float(rng.uniform(low, high))

        return draw
    return None


@dataclass
class SideChannels:
    """Unity's SideChannelManager with the channels a real build registers by default."""

    parameters: Parameters
    engine: EngineSettings = field(default_factory=EngineSettings)
    unknown: list[tuple[uuid.UUID, bytes]] = field(default_factory=list)
    analytics_messages: int = 0

    def receive(self, blob: bytes) -> None:
        for channel, payload in split_records(blob):
            if channel == ENGINE_CONFIGURATION:
                self._engine(Reader(payload))
            elif channel == ENVIRONMENT_PARAMETERS:
                self._parameter(Reader(payload))
            elif channel == TRAINING_ANALYTICS:
                self.analytics_messages += 1
            else:
                log.info("caching side-channel message for unregistered channel %s", channel)
                self.unknown.append((channel, payload))

    def _engine(self, reader: Reader) -> None:
        kind = reader.int32()
        engine = self.engine
        if kind == 0:
            engine.width, engine.height = reader.int32(), reader.int32()
        elif kind == 1:
            engine.quality_level = reader.int32()
        elif kind == 2:
            engine.time_scale = max(1.0, reader.float32())  # Unity clamps to >= 1
        elif kind == 3:
            engine.target_frame_rate = reader.int32()
        elif kind == 4:
            engine.capture_frame_rate = reader.int32()
        else:
            log.warning("unknown engine configuration type %d", kind)
            return
        log.info("engine configuration: %s", engine)

    def _parameter(self, reader: Reader) -> None:
        key, data_type = reader.string(), reader.int32()
        if data_type == 0:
            value = reader.float32()
            self.parameters.values[key] = value
            log.info("environment parameter %s = %s", key, value)
        elif data_type == 1:
            seed, sampler_type = reader.int32(), reader.int32()
            sampler = _sampler(sampler_type, seed, reader)
            if sampler is None:
                log.warning("unknown sampler type %d for %s", sampler_type, key)
                return
            self.parameters.values[key] = sampler
            log.info("environment parameter %s sampled (type %d, seed %d)", key, sampler_type, seed)
        else:
            log.warning("unknown environment parameter type %d for %s", data_type, key)


def encode_stats(stats: Iterable[tuple[str, float, StatsMethod]]) -> bytes:
    """Stats side-channel records, one per ``StatsRecorder.Add``."""
    return b"".join(
        frame(STATS, write_string(key) + struct.pack("<fi", value, int(method)))
        for key, value, method in stats
    )
