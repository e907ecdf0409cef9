"""Demo files built the way Unity's C# recorder builds them, independently of our writer.

:class:`UnityStyleWriter` replays the stream operations of ``DemonstrationWriter``
(com.unity.ml-agents, Runtime/Demonstrations/DemonstrationWriter.cs): ``Initialize`` writes
a first delimited metadata (name only) at byte 0 and seeks to byte 33 for the delimited
brain parameters; ``Record`` appends one delimited ``AgentInfoActionPairProto``; ``Close``
counts one more episode, writes the final metadata's bytes (undelimited) at the end, seeks
back to 0 and writes it delimited there. The records are hand-built protos, as
``GrpcExtensions.ToInfoActionPairProto`` and ``GetObservationProto`` fill them.
"""

from __future__ import annotations

import io

import numpy as np
from mlagents_envs.communicator_objects.agent_action_pb2 import AgentActionProto
from mlagents_envs.communicator_objects.agent_info_action_pair_pb2 import (
    AgentInfoActionPairProto,
)
from mlagents_envs.communicator_objects.agent_info_pb2 import AgentInfoProto
from mlagents_envs.communicator_objects.brain_parameters_pb2 import (
    ActionSpecProto,
    BrainParametersProto,
)
from mlagents_envs.communicator_objects.demonstration_meta_pb2 import DemonstrationMetaProto
from mlagents_envs.communicator_objects.observation_pb2 import PNG, ObservationProto
from PIL import Image

META_DATA_BYTES = 32  # DemonstrationWriter.MetaDataBytes


def varint(value: int) -> bytes:
    out = bytearray()
    while value > 0x7F:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def write_delimited(stream: io.BytesIO, message) -> None:
    body = message.SerializeToString()
    stream.write(varint(len(body)) + body)


class UnityStyleWriter:
    def __init__(self, name: str, brain: BrainParametersProto, api_version: int = 1) -> None:
        self.stream = io.BytesIO()
        self.name, self.api_version = name, api_version
        self.steps = self.episodes = 0
        self.cumulative = np.float32(0)
        write_delimited(self.stream, self.meta())
        self.stream.seek(META_DATA_BYTES + 1)
        write_delimited(self.stream, brain)

    def meta(self, mean_reward: float = 0.0) -> DemonstrationMetaProto:
        return DemonstrationMetaProto(
            api_version=self.api_version,
            demonstration_name=self.name,
            number_steps=self.steps,
            number_episodes=self.episodes,
            mean_reward=mean_reward,
        )

    def record(self, pair: AgentInfoActionPairProto) -> None:
        self.steps += 1
        self.cumulative = np.float32(self.cumulative + np.float32(pair.agent_info.reward))
        if pair.agent_info.done:
            self.episodes += 1
        write_delimited(self.stream, pair)

    def close(self) -> bytes:
        self.episodes += 1  # Close() always ends one more episode
        meta = self.meta(float(self.cumulative / np.float32(self.episodes)))
        self.stream.write(meta.SerializeToString())
        self.stream.seek(0)
        write_delimited(self.stream, meta)
        return self.stream.getvalue()

    def unclosed(self) -> bytes:
        """What is on disk when Unity stopped without closing the writer."""
        return self.stream.getvalue()


def brain(
    name: str, continuous: int = 0, branches: tuple[int, ...] = (), deprecated_only: bool = False
) -> BrainParametersProto:
    """``BrainParameters.ToProto(name, false)``, deprecated fields synced from the action spec
    (``deprecated_only``: a file from before the action spec, which has only those)."""
    proto = BrainParametersProto(brain_name=name, is_training=False)
    if not deprecated_only:
        proto.action_spec.CopyFrom(
            ActionSpecProto(
                num_continuous_actions=continuous,
                num_discrete_actions=len(branches),
                discrete_branch_sizes=branches,
            )
        )
    if continuous == 0:
        proto.vector_action_size_deprecated.extend(branches)
    elif not branches:
        proto.vector_action_size_deprecated.append(continuous)
        proto.vector_action_space_type_deprecated = 1
    return proto


def vector_obs(values, name: str = "VectorSensor_size4") -> ObservationProto:
    values = np.asarray(values, np.float32)
    proto = ObservationProto(shape=values.shape, dimension_properties=[1] * values.ndim, name=name)
    proto.float_data.data.extend(values.ravel().tolist())
    return proto


def png_obs(chw_uint8: np.ndarray, name: str = "CameraSensor", mapping=()) -> ObservationProto:
    """A camera (or grid) sensor: RGB PNGs made with Pillow, as Texture2D.EncodeToPNG."""
    channels = chw_uint8.shape[0]
    padded = -(-channels // 3) * 3
    planes = np.concatenate(
        [chw_uint8, np.zeros((padded - channels, *chw_uint8.shape[1:]), np.uint8)]
    )
    data = b""
    for first in range(0, padded, 3):
        out = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(planes[first : first + 3].transpose(1, 2, 0))).save(
            out, format="PNG"
        )
        data += out.getvalue()
    return ObservationProto(
        shape=chw_uint8.shape,
        compression_type=PNG,
        compressed_data=data,
        compressed_channel_mapping=list(mapping),
        dimension_properties=[1, 2, 2],
        name=name,
    )


def pair(
    observations,
    reward: float = 0.0,
    done: bool = False,
    max_step: bool = False,
    agent_id: int = 0,
    mask=(),
    continuous=(),
    discrete=(),
    deprecated=(),
) -> AgentInfoActionPairProto:
    info = AgentInfoProto(
        reward=reward,
        max_step_reached=max_step,
        done=done,
        id=agent_id,
        action_mask=list(mask),
    )
    info.observations.extend(observations)
    action = AgentActionProto(
        continuous_actions=list(continuous),
        discrete_actions=list(discrete),
        vector_actions_deprecated=list(deprecated),
    )
    return AgentInfoActionPairProto(agent_info=info, action_info=action)
