"""Unit tests of unitysim's Unity-side pieces: side-channel decoding, faults, launchers."""

from __future__ import annotations

import argparse
import os
import stat
import uuid

import numpy as np
import pytest
from mlagents_envs.side_channel.engine_configuration_channel import EngineConfigurationChannel
from mlagents_envs.side_channel.environment_parameters_channel import (
    EnvironmentParametersChannel,
)
from mlagents_envs.side_channel.side_channel_manager import SideChannelManager
from mlagents_envs.side_channel.stats_side_channel import StatsSideChannel

from unitysim.envs.base import Parameters, StatsMethod
from unitysim.faults import Faults
from unitysim.launcher import build
from unitysim.side_channels import (
    SideChannelError,
    SideChannels,
    encode_stats,
    frame,
    split_records,
)


def python_bytes(*channels) -> bytes:
    return bytes(SideChannelManager(list(channels)).generate_side_channel_messages())


def test_engine_configuration_from_python_is_decoded():
    engine = EngineConfigurationChannel()
    engine.set_configuration_parameters(
        width=84,
        height=64,
        quality_level=3,
        time_scale=0.5,
        target_frame_rate=30,
        capture_frame_rate=50,
    )
    channels = SideChannels(Parameters())
    channels.receive(python_bytes(engine))
    settings = channels.engine
    assert (settings.width, settings.height, settings.quality_level) == (84, 64, 3)
    assert settings.time_scale == 1.0  # Unity clamps the time scale to >= 1
    assert (settings.target_frame_rate, settings.capture_frame_rate) == (30, 50)


def test_environment_parameters_values_and_seeded_samplers():
    params = EnvironmentParametersChannel()
    params.set_float_parameter("gravity", 4.5)
    params.set_uniform_sampler_parameters("mass", 1.0, 2.0, 1234)
    params.set_gaussian_sampler_parameters("scale", 10.0, 0.5, 7)
    params.set_multirangeuniform_sampler_parameters("len", [(1.0, 2.0), (5.0, 6.0)], 9)
    blob = python_bytes(params)

    def draws() -> dict[str, list[float]]:
        parameters = Parameters()
        SideChannels(parameters).receive(blob)
        return {key: [parameters.get(key, -1.0) for _ in range(200)] for key in parameters.values}

    first, second = draws(), draws()
    assert first == second  # samplers are seeded by the seed Python sent
    assert set(first["gravity"]) == {4.5}
    mass = np.array(first["mass"])
    assert mass.min() >= 1.0 and mass.max() <= 2.0 and mass.std() > 0.2
    assert abs(np.mean(first["scale"]) - 10.0) < 0.2
    lengths = np.array(first["len"])
    assert np.all(((lengths >= 1) & (lengths <= 2)) | ((lengths >= 5) & (lengths <= 6)))
    assert (lengths < 3).any() and (lengths > 4).any()
    assert Parameters().get("missing", 3.0) == 3.0


def test_unknown_channels_are_cached_and_analytics_ignored():
    channels = SideChannels(Parameters())
    custom = uuid.uuid4()
    channels.receive(frame(custom, b"hello") + frame(custom, b"again"))
    assert channels.unknown == [(custom, b"hello"), (custom, b"again")]


def test_truncated_side_channel_bytes_are_rejected():
    blob = frame(uuid.uuid4(), b"payload")
    with pytest.raises(SideChannelError, match="truncated"):
        split_records(blob[:-2])
    with pytest.raises(SideChannelError, match="truncated"):
        split_records(blob[:10])


def test_stats_reach_python_decoded():
    stats = StatsSideChannel()
    blob = encode_stats([("Score", 2.5, StatsMethod.AVERAGE), ("Goals", 3.0, StatsMethod.SUM)])
    SideChannelManager([stats]).process_side_channel_message(blob)
    received = stats.get_and_reset_stats()
    assert [(v, int(m.value)) for v, m in received["Score"]] == [(2.5, 0)]
    assert [(v, int(m.value)) for v, m in received["Goals"]] == [(3.0, 2)]


def test_faults_from_flags_and_environment(monkeypatch):
    parser = argparse.ArgumentParser()
    Faults.add_arguments(parser)
    monkeypatch.setenv("UNITYSIM_HANG_AFTER", "7")
    monkeypatch.setenv("UNITYSIM_DELAY_MS", "12.5")
    monkeypatch.setenv("UNITYSIM_CRASH_AFTER", "99")
    args = parser.parse_args(["--sim-crash-after", "3", "--sim-communication-version", "2.0.0"])
    faults = Faults.from_arguments(args)
    assert faults.crash_after == 3  # the flag wins over the environment
    assert faults.hang_after == 7 and faults.delay_ms == 12.5
    assert faults.communication_version == "2.0.0"
    assert faults.due(faults.crash_after, 3) and not faults.due(faults.crash_after, 2)
    assert not faults.due(None, 10**6)


def test_launchers_are_executable_exec_scripts(tmp_path):
    (path,) = build(tmp_path, ["3DBall"])
    assert path.name == "3DBall.x86_64"
    assert os.stat(path).st_mode & stat.S_IXUSR
    text = path.read_text()
    assert text.startswith("#!/bin/sh") and "exec " in text and '"$@"' in text
    mtime = path.stat().st_mtime_ns
    build(tmp_path, ["3DBall"])  # unchanged content: the file is left alone
    assert path.stat().st_mtime_ns == mtime
    with pytest.raises(ValueError, match="unknown unitysim environment 'Nope'"):
        build(tmp_path, ["Nope"])
