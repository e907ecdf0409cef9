"""Protobuf on the Unity side: environment batches to ``UnityMessageProto`` and back.

The only module of unitysim that knows the generated message classes (they import
because ``unitysim/__init__.py`` activates ``mlagents_compat``). Field meanings are
in the protocol note: ``docs`` of the project and ``unity-protocol.md`` §3.

The per-step output built here (:func:`rl_output`) is the reference encoder; the player
sends the bytes of the fast one in ``unitysim/wire.py``, which tests hold equal to it.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from mlagents_envs.communicator_objects.agent_info_pb2 import AgentInfoProto
from mlagents_envs.communicator_objects.brain_parameters_pb2 import (
    ActionSpecProto,
    BrainParametersProto,
)
from mlagents_envs.communicator_objects.capabilities_pb2 import UnityRLCapabilitiesProto
from mlagents_envs.communicator_objects.header_pb2 import HeaderProto
from mlagents_envs.communicator_objects.observation_pb2 import NONE, PNG, ObservationProto
from mlagents_envs.communicator_objects.unity_message_pb2 import UnityMessageProto
from mlagents_envs.communicator_objects.unity_output_pb2 import UnityOutputProto
from mlagents_envs.communicator_objects.unity_rl_initialization_output_pb2 import (
    UnityRLInitializationOutputProto,
)
from mlagents_envs.communicator_objects.unity_rl_output_pb2 import UnityRLOutputProto

from unitysim import png
from unitysim.envs.base import Actions, AgentInfos, Behavior, Sensor

COMMUNICATION_VERSION = "1.5.0"
PACKAGE_VERSION = "3.0.0"  # the C# package version of Release 22
STEP, RESET, QUIT = 0, 1, 2


__all__ = [
    "COMMUNICATION_VERSION",
    "Input",
    "UnityMessageProto",
    "handshake_output",
    "parse_input",
    "rl_output",
    "status_message",
]


def status_message(status: int) -> UnityMessageProto:
    """A bare message: 200 is the empty second handshake message, 400 a close."""
    return UnityMessageProto(header=HeaderProto(status=status))


def handshake_output(communication_version: str = COMMUNICATION_VERSION) -> UnityMessageProto:
    """U1: academy parameters as real Unity fills them, all capabilities on."""
    capabilities = UnityRLCapabilitiesProto(
        baseRLCapabilities=True,
        concatenatedPngObservations=True,
        compressedChannelMapping=True,
        hybridActions=True,
        trainingAnalytics=True,
        variableLengthObservation=True,
        multiAgentGroups=True,
    )
    init = UnityRLInitializationOutputProto(
        name="AcademySingleton",
        communication_version=communication_version,
        package_version=PACKAGE_VERSION,
        capabilities=capabilities,
    )
    return UnityMessageProto(
        header=HeaderProto(status=200),
        unity_output=UnityOutputProto(rl_initialization_output=init),
    )


def brain_parameters(behavior: Behavior) -> BrainParametersProto:
    return BrainParametersProto(
        brain_name=behavior.name,
        is_training=True,
        action_spec=ActionSpecProto(
            num_continuous_actions=behavior.continuous,
            num_discrete_actions=len(behavior.branches),
            discrete_branch_sizes=list(behavior.branches),
        ),
    )


def _observations(sensor: Sensor, batch: np.ndarray) -> list[ObservationProto]:
    common = {
        "shape": sensor.shape,
        "dimension_properties": sensor.dimension_properties,
        "observation_type": sensor.observation_type,
        "name": sensor.name,
    }
    if sensor.png:  # its channels as PNGs; a StackingSensor's frames each their own, mapped
        mapping = list(sensor.channel_mapping)
        return [
            ObservationProto(
                compression_type=PNG,
                compressed_data=b"".join(
                    png.encode(frame) for frame in row.reshape(sensor.stacks, -1, *row.shape[1:])
                ),
                compressed_channel_mapping=mapping,
                **common,
            )
            for row in batch
        ]
    return [
        ObservationProto(
            compression_type=NONE, float_data=ObservationProto.FloatData(data=row), **common
        )
        for row in batch.reshape(len(batch), int(np.prod(sensor.shape))).tolist()
    ]


def agent_infos(behavior: Behavior, infos: AgentInfos) -> list[AgentInfoProto]:
    per_sensor = [_observations(s, o) for s, o in zip(behavior.sensors, infos.obs, strict=True)]
    masks = (
        infos.action_mask.tolist()
        if infos.action_mask is not None and behavior.branches
        else [[]] * len(infos)
    )
    return [
        AgentInfoProto(
            reward=reward,
            done=done,
            max_step_reached=max_step,
            id=agent_id,
            action_mask=mask,
            observations=observations,
            group_id=group_id,
            group_reward=group_reward,
        )
        for reward, done, max_step, agent_id, mask, group_id, group_reward, *observations in zip(
            infos.reward.tolist(),
            infos.done.tolist(),
            infos.max_step_reached.tolist(),
            infos.agent_id.tolist(),
            masks,
            infos.group_id.tolist(),
            infos.group_reward.tolist(),
            *per_sensor,
            strict=True,
        )
    ]


def rl_output(
    behaviors: dict[str, Behavior],
    output: dict[str, AgentInfos],
    announce: list[Behavior],
    side_channel: bytes = b"",
) -> UnityMessageProto:
    """U3...: agent infos per behavior (an entry for every behavior seen so far), side
    channel bytes, and brain parameters of behaviors reported for the first time."""
    rl = UnityRLOutputProto(side_channel=side_channel)
    for name, infos in output.items():
        rl.agentInfos[name].value.extend(agent_infos(behaviors[name], infos))
    unity_output = UnityOutputProto(rl_output=rl)
    if announce:
        unity_output.rl_initialization_output.brain_parameters.extend(
            brain_parameters(b) for b in announce
        )
    return UnityMessageProto(header=HeaderProto(status=200), unity_output=unity_output)


@dataclass(frozen=True)
class Input:
    """What Python said: header status, command, per-behavior actions, side-channel bytes."""

    status: int
    command: int
    actions: dict[str, Actions]
    side_channel: bytes
    seed: int | None = None
    num_areas: int | None = None
    communication_version: str | None = None


def parse_input(message: UnityMessageProto, behaviors: dict[str, Behavior]) -> Input:
    unity_input = message.unity_input
    if unity_input.HasField("rl_initialization_input"):
        init = unity_input.rl_initialization_input
        return Input(
            status=message.header.status,
            command=STEP,
            actions={},
            side_channel=b"",
            seed=init.seed,
            num_areas=init.num_areas,
            communication_version=init.communication_version,
        )
    rl = unity_input.rl_input
    actions: dict[str, Actions] = {}
    for name, listed in rl.agent_actions.items():
        behavior = behaviors.get(name)
        if behavior is None:
            continue
        rows = listed.value
        actions[name] = Actions(
            _gather(rows, "continuous_actions", behavior.continuous, np.float32),
            _gather(rows, "discrete_actions", len(behavior.branches), np.int32),
        )
    return Input(
        status=message.header.status,
        command=rl.command,
        actions=actions,
        side_channel=rl.side_channel,
    )


def _gather(rows: Sequence[object], field: str, width: int, dtype: type) -> np.ndarray:
    """One repeated field of every AgentActionProto as an (n, width) array, in one pass.

    A total that does not fit (n, width) raises ValueError, as before; rows of unequal
    lengths adding up to n * width are not told apart (mlagents_envs never sends them)."""
    n = len(rows)
    if n == 0 or width == 0:  # (Python sends no values for an action type without any)
        return np.zeros((n, width), dtype=dtype)
    values = np.fromiter(
        itertools.chain.from_iterable([getattr(row, field) for row in rows]), dtype=dtype
    )
    return values.reshape(n, width)
