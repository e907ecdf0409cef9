"""The fast Unity -> Python encoder against the protobuf-object reference, and AgentInfos.

``wire.encode_rl_output`` writes wire bytes by hand for speed; whatever it writes must
parse (``UnityMessageProto.FromString``) to exactly the message the reference builder
``messages.rl_output`` makes. Hand-picked cases cover each field and corner; a seeded fuzz
loop covers combinations. Plain unit tests: no processes, no gRPC. The other direction
(Python's input) is tested in ``test_wire_input.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from mlagents_envs.communicator_objects.unity_message_pb2 import UnityMessageProto

from unitysim import messages, png, wire
from unitysim.envs.base import (
    GOAL_SIGNAL,
    NONE_DIM,
    AgentInfos,
    Behavior,
    Sensor,
)

VECTOR = Sensor.vector("VectorSensor_size8", 8)
ENTITIES = Sensor("BufferSensor", (4, 5), (4, NONE_DIM))  # rank 2, variable length
GOAL = Sensor.vector("GoalSignal", 2, observation_type=GOAL_SIGNAL)
CAMERA = Sensor.visual("CameraSensor", 3, 6, 5)
CAMERA4 = Sensor.visual("Grid", 4, 5, 7)  # 4 channels: two concatenated PNGs
UNNAMED = Sensor("", (3,), ())  # no name, no dimension properties: both left out

CONTINUOUS = Behavior("Ball?team=0", (VECTOR,), continuous=2)
HYBRID = Behavior("Hybrid?team=1", (ENTITIES, GOAL, UNNAMED), continuous=1, branches=(3, 2))
VISUAL = Behavior("Visual?team=0", (CAMERA, GOAL, CAMERA4), branches=(5,))


def infos(
    behavior: Behavior, n: int, rng: np.random.Generator, *, png_ok: bool = True, **kwargs
) -> AgentInfos:
    obs = []
    for sensor in behavior.sensors:
        if sensor.png:
            assert png_ok
            obs.append(rng.random((n, *sensor.shape), dtype=np.float32))
        else:
            obs.append(rng.normal(0, 3, (n, *sensor.shape)).astype(np.float32))
    kwargs.setdefault("reward", rng.normal(size=n).astype(np.float32))
    if behavior.branches and "action_mask" not in kwargs:
        kwargs["action_mask"] = rng.random((n, behavior.mask_size)) < 0.3
    return AgentInfos.build(np.arange(n, dtype=np.int32) * 7, obs, **kwargs)


def assert_same(
    behaviors: list[Behavior],
    output: dict[str, AgentInfos],
    announce: list[Behavior] | None = None,
    side_channel: bytes = b"",
) -> bytes:
    by_name = {b.name: b for b in behaviors}
    announce = announce or []
    fast = wire.encode_rl_output(by_name, output, announce, side_channel)
    reference = messages.rl_output(by_name, output, announce, side_channel)
    parsed = UnityMessageProto.FromString(fast)
    assert parsed == reference, _first_difference(parsed, reference)
    return fast


def _first_difference(parsed: UnityMessageProto, reference: UnityMessageProto) -> str:
    a, b = str(parsed).splitlines(), str(reference).splitlines()
    for index, (x, y) in enumerate(zip(a, b, strict=False)):
        if x != y:
            return f"line {index}: fast {x!r} != reference {y!r}"
    return f"fast has {len(a)} lines, reference {len(b)}"


def test_float_sensor_rank_1_same_bytes_as_protobuf():
    rng = np.random.default_rng(0)
    output = {CONTINUOUS.name: infos(CONTINUOUS, 12, rng)}
    fast = assert_same([CONTINUOUS], output, [CONTINUOUS])
    # Canonical encoding, field for field: protobuf writes exactly these bytes too.
    by_name = {CONTINUOUS.name: CONTINUOUS}
    reference = messages.rl_output(by_name, output, [CONTINUOUS]).SerializeToString()
    assert fast == reference


def test_float_sensors_of_rank_2_goal_signal_and_unnamed():
    rng = np.random.default_rng(1)
    assert_same([HYBRID], {HYBRID.name: infos(HYBRID, 5, rng)})


def test_png_sensors_rank_3_three_and_four_channels():
    rng = np.random.default_rng(2)
    fast = assert_same([VISUAL], {VISUAL.name: infos(VISUAL, 3, rng)}, [VISUAL])
    agent = UnityMessageProto.FromString(fast).unity_output.rl_output.agentInfos[VISUAL.name]
    observations = agent.value[0].observations
    assert observations[0].compressed_data.startswith(b"\x89PNG")
    assert observations[2].compressed_data.count(b"IEND") == 2
    assert observations[1].HasField("float_data")


@pytest.mark.parametrize("channels", [1, 3, 4, 7])
def test_png_writer_round_trips_through_mlagents(channels):
    """The PNGs are written with zlib by hand: mlagents_envs (Pillow) must read them back."""
    from mlagents_envs.rpc_utils import process_pixels

    rng = np.random.default_rng(channels)
    chw = (rng.integers(0, 256, (channels, 9, 11)) / 255.0).astype(np.float32)
    decoded = process_pixels(png.encode(chw), channels)
    if channels == 1:  # Python averages the RGB of a one-channel image (padded with zeros)
        np.testing.assert_allclose(decoded[0], chw[0] / 3.0, atol=1 / 255)
    else:
        np.testing.assert_array_equal(decoded, chw)
    batch = rng.random((3, channels, 5, 4), dtype=np.float32)
    assert png.encode_batch(batch) == [png.encode(row) for row in batch]


def test_masks_present_absent_and_ignored_without_branches():
    rng = np.random.default_rng(3)
    assert_same([HYBRID], {HYBRID.name: infos(HYBRID, 4, rng, action_mask=None)})
    full = np.ones((4, HYBRID.mask_size), dtype=bool)
    assert_same([HYBRID], {HYBRID.name: infos(HYBRID, 4, rng, action_mask=full)})
    # A mask given to a behavior without discrete actions is not sent (as Unity does).
    stray = infos(CONTINUOUS, 4, rng, action_mask=np.ones((4, 3), dtype=bool))
    fast = assert_same([CONTINUOUS], {CONTINUOUS.name: stray})
    rl = UnityMessageProto.FromString(fast).unity_output.rl_output
    assert not rl.agentInfos[CONTINUOUS.name].value[0].action_mask


def test_empty_behaviors_are_listed():
    rng = np.random.default_rng(4)
    output = {
        CONTINUOUS.name: infos(CONTINUOUS, 0, rng),
        VISUAL.name: infos(VISUAL, 0, rng),
        HYBRID.name: infos(HYBRID, 2, rng),
    }
    fast = assert_same([CONTINUOUS, VISUAL, HYBRID], output)
    rl = UnityMessageProto.FromString(fast).unity_output.rl_output
    assert set(rl.agentInfos) == {CONTINUOUS.name, VISUAL.name, HYBRID.name}  # (a map)
    assert len(rl.agentInfos[CONTINUOUS.name].value) == 0


def test_no_behaviors_at_all():
    assert_same([], {})
    assert_same([], {}, side_channel=b"\x01\x02")


def test_terminal_then_decision_rows_for_the_same_agent():
    rng = np.random.default_rng(5)
    terminal = infos(
        CONTINUOUS,
        3,
        rng,
        reward=np.array([-1.0, 0.1, 0.0], np.float32),
        done=True,
        max_step_reached=np.array([False, True, True]),
    )
    decision = infos(CONTINUOUS, 3, rng, reward=0.0)
    both = AgentInfos.concat([terminal, decision])
    fast = assert_same([CONTINUOUS], {CONTINUOUS.name: both})
    rows = UnityMessageProto.FromString(fast).unity_output.rl_output.agentInfos
    values = rows[CONTINUOUS.name].value
    assert [v.done for v in values] == [True] * 3 + [False] * 3
    assert [v.max_step_reached for v in values] == [False, True, True] + [False] * 3
    assert [v.id for v in values] == [0, 7, 14, 0, 7, 14]


def test_brain_parameter_announcements():
    rng = np.random.default_rng(6)
    output = {b.name: infos(b, 2, rng) for b in (CONTINUOUS, HYBRID, VISUAL)}
    fast = assert_same([CONTINUOUS, HYBRID, VISUAL], output, [HYBRID, VISUAL])
    init = UnityMessageProto.FromString(fast).unity_output.rl_initialization_output
    assert [p.brain_name for p in init.brain_parameters] == [HYBRID.name, VISUAL.name]
    assert list(init.brain_parameters[0].action_spec.discrete_branch_sizes) == [3, 2]
    # Without announcements there is no rl_initialization_output at all.
    plain = UnityMessageProto.FromString(assert_same([CONTINUOUS], {}))
    assert not plain.unity_output.HasField("rl_initialization_output")
    assert plain.unity_output.HasField("rl_output")


def test_side_channel_bytes():
    rng = np.random.default_rng(7)
    blob = bytes(rng.integers(0, 256, 300, dtype=np.uint8))  # a multi-byte length
    fast = assert_same([CONTINUOUS], {CONTINUOUS.name: infos(CONTINUOUS, 2, rng)}, [], blob)
    assert UnityMessageProto.FromString(fast).unity_output.rl_output.side_channel == blob


def test_scalar_corners_ids_groups_and_signed_zero():
    rng = np.random.default_rng(8)
    n = 6
    batch = infos(
        HYBRID,
        n,
        rng,
        reward=np.array([0.0, -0.0, 1e-45, np.inf, -3.5, 0.1], np.float32),
        group_id=np.array([0, 1, -1, 127, 128, 2**31 - 1], np.int32),
        group_reward=np.array([-0.0, 0.0, 2.0, 0.0, -1.0, 0.0], np.float32),
    )
    batch.agent_id[:] = [0, -5, 127, 128, 300_000, -(2**31)]
    assert_same([HYBRID], {HYBRID.name: batch})


def test_nan_observations_same_bytes_as_protobuf():
    """NaN never compares equal, so compare bytes (the player's NaN fault sends these)."""
    rng = np.random.default_rng(9)
    batch = infos(CONTINUOUS, 3, rng)
    batch.obs[0][1, 2:5] = np.nan
    by_name = {CONTINUOUS.name: CONTINUOUS}
    fast = wire.encode_rl_output(by_name, {CONTINUOUS.name: batch}, [])
    reference = messages.rl_output(by_name, {CONTINUOUS.name: batch}, []).SerializeToString()
    assert fast == reference


def _random_sensor(rng: np.random.Generator, index: int) -> Sensor:
    rank = int(rng.integers(1, 4))
    if rank == 3 and rng.random() < 0.5:
        return Sensor.visual(f"Camera{index}", int(rng.integers(1, 7)), 4, 3)
    shape = tuple(int(s) for s in rng.integers(0 if rng.random() < 0.1 else 1, 7, rank))
    dims = tuple(int(d) for d in rng.choice([1, 2, 4], rank)) if rng.random() < 0.8 else ()
    name = f"Sensor{index}" * int(rng.integers(0, 3))
    return Sensor(name, shape, dims, observation_type=int(rng.integers(0, 2)), png=False)


def _random_floats(rng: np.random.Generator, size: int) -> np.ndarray:
    values = rng.normal(0, 10, size).astype(np.float32)
    special = np.array([0.0, -0.0, np.inf, -np.inf, 1e-45, 3.4e38], np.float32)
    pick = rng.random(size) < 0.2
    values[pick] = rng.choice(special, int(pick.sum()))
    return values


def test_fuzz_against_reference():
    rng = np.random.default_rng(2024)
    for case in range(150):
        behaviors = []
        for b in range(int(rng.integers(0, 4))):
            sensors = tuple(_random_sensor(rng, i) for i in range(int(rng.integers(0, 4))))
            branches = tuple(int(s) for s in rng.integers(1, 6, int(rng.integers(0, 3))))
            behaviors.append(
                Behavior(f"B{case}_{b}?team={b}", sensors, int(rng.integers(0, 4)), branches)
            )
        output = {}
        for behavior in behaviors:
            n = int(rng.integers(0, 20))
            obs = []
            for sensor in behavior.sensors:
                if sensor.png:
                    obs.append(rng.random((n, *sensor.shape), dtype=np.float32))
                else:
                    size = n * int(np.prod(sensor.shape))
                    obs.append(_random_floats(rng, size).reshape(n, *sensor.shape))
            mask = None
            if rng.random() < 0.7:
                mask = rng.random((n, behavior.mask_size)) < 0.5
            ids = (
                rng.integers(-(2**31), 2**31, n) if rng.random() < 0.3 else rng.integers(0, 300, n)
            )
            output[behavior.name] = AgentInfos.build(
                ids.astype(np.int32),
                obs,
                reward=_random_floats(rng, n),
                done=rng.random(n) < 0.3,
                max_step_reached=rng.random(n) < 0.2,
                group_id=rng.integers(-3, 200, n).astype(np.int32) if rng.random() < 0.3 else 0,
                group_reward=_random_floats(rng, n) if rng.random() < 0.3 else 0.0,
                action_mask=mask,
            )
        announce = [b for b in behaviors if rng.random() < 0.5]
        side = bytes(rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8))
        assert_same(behaviors, output, announce, side)


def test_encode_output_is_the_fast_encoder_and_to_bytes_passes_bytes():
    assert wire.encode_output is wire.encode_rl_output  # unless the variable is set
    assert wire.to_bytes(b"\x0a\x00") == b"\x0a\x00"
    assert wire.to_bytes(messages.status_message(200)) == b"\x0a\x03\x08\xc8\x01"
    assert wire.to_bytes(messages.status_message(400)) == b"\x0a\x03\x08\x90\x03"


# --- AgentInfos.build (every message goes through it) --------------------------------------


def test_build_broadcasts_scalars_and_copies_arrays():
    reward = np.array([1.0, 2.0], np.float32)
    obs = np.zeros((2, 3), np.float32)
    built = AgentInfos.build(np.array([4, 5]), [obs], reward=reward, done=True, group_id=2)
    reward[:] = 0.0  # an environment may reuse its buffer right after
    assert built.reward.tolist() == [1.0, 2.0]
    assert built.done.tolist() == [True, True] and built.done.dtype == np.bool_
    assert built.group_id.tolist() == [2, 2] and built.group_id.dtype == np.int32
    assert built.max_step_reached.tolist() == [False, False]
    assert built.group_reward.dtype == np.float32 and built.agent_id.dtype == np.int32
    assert built.obs[0] is obs  # float32 observations are taken as they are
    mixed = AgentInfos.build([[1], [2]], [[[1.0], [2.0]]], reward=[0.5], done=np.array([1, 0]))
    assert mixed.agent_id.shape == (2,) and mixed.obs[0].dtype == np.float32
    assert mixed.reward.tolist() == [0.5, 0.5] and mixed.done.tolist() == [True, False]


def test_build_shares_constant_fields_read_only_and_keeps_signed_zero():
    first = AgentInfos.build(np.arange(3), [np.zeros((3, 1), np.float32)])
    second = AgentInfos.build(np.arange(3), [np.zeros((3, 1), np.float32)])
    assert first.done is second.done and first.group_reward is second.group_reward
    with pytest.raises(ValueError):
        first.done[0] = True  # shared: nobody may write it
    negative = AgentInfos.build(np.arange(3), [np.zeros((3, 1), np.float32)], reward=-0.0)
    assert np.signbit(negative.reward).all() and not np.signbit(first.reward).any()


def test_sensors_and_behaviors_built_with_lists_still_encode():
    """Caches are keyed by Sensor / Behavior; unhashable ones are encoded without them."""
    rng = np.random.default_rng(11)
    sensor = Sensor("Listed", [2, 3], [1, 1])  # type: ignore[arg-type]
    behavior = Behavior("Listed?team=0", [sensor, GOAL], branches=[2])  # type: ignore[arg-type]
    assert_same([behavior], {behavior.name: infos(behavior, 3, rng)}, [behavior])
