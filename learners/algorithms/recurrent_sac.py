"""SAC with memory (``network_settings.memory``), as mlagents-learn trains a recurrent SAC.

What differs from ``learners/algorithms/sac.py``:

- The replay buffer holds sequences of ``sequence_length`` steps, cut from each stored
  trajectory piece from its start, the last one padded at its end
  (``learners.algorithms.recurrent_ppo.sequences``), with the memory each step's decision read
  (workers carry it, ``rollout/collecting/segments.py``). A gradient step samples
  ``batch_size / sequence_length`` sequences (at least one), as ML-Agents' SAC does.
- The actor runs over each sequence from the memory stored at its first step, and over
  the states after its steps from the memory after that first step.
- Each Q network and its target has an LSTM of its own and runs over the sequence from
  zero memory, as ML-Agents' Q networks do. The target Qs run over the sequence's first
  state, then the states after its steps, so their memory has seen the step before.
- SAC's losses, unchanged, on the sequences' real steps (the padding left out).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict

from batches import keys
from learners.algorithms.recurrent_ppo import sequences
from learners.algorithms.sac import SAC
from learners.algorithms.sac_terms import CONTINUOUS_ACTION
from learners.networks.q_networks import RecurrentQNetwork

if TYPE_CHECKING:
    from torch import nn

    from learners.networks.policies import ActorCritic
    from learners.trainer_config.settings import TrainerSettings

VALID = "valid"  # [S, L] bool: a real step (else padding)


@dataclass(frozen=True)
class SequenceInputs:
    """What the passes read of sampled sequences ``[B, L]``: each sensor's observations
    ``[B, L, ...]`` (or ``[B, L + 1, ...]``: the first state, then the states after each
    step), and the sequences themselves (their memories, real steps, stored actions)."""

    sensors: list[torch.Tensor]
    sequences: TensorDict

    @property
    def skipped(self) -> int:
        """Leading outputs that belong to no step of the sequences (the first state)."""
        return self.sensors[0].shape[1] - self.sequences.shape[1]


class RecurrentSAC(SAC):
    q_network = RecurrentQNetwork

    def __init__(
        self, network: ActorCritic, settings: TrainerSettings, *args: Any, **kwargs: Any
    ) -> None:
        """As ``SAC``'s (``compute``, ``experts`` after the settings)."""
        memory = settings.network_settings.memory
        assert memory is not None and network.lstm is not None
        self.length = memory.sequence_length
        super().__init__(network, settings, *args, **kwargs)

    def items(self, steps: int) -> int:
        return max(1, steps // self.length)

    def store(self, transitions: TensorDict, segment: TensorDict) -> None:
        cut = sequences(segment[keys.NEXT, keys.DONE].reshape(-1), self.length)
        items = transitions[cut.rows]  # [S, L]
        items[VALID] = cut.valid
        items[keys.MEMORY] = segment[keys.MEMORY][cut.rows]
        self.buffer.extend(items)

    def stored_steps(self) -> int:
        return len(self.buffer) * self.length

    def steps(self, sampled: TensorDict) -> TensorDict:
        """The real steps of sampled sequences ``[B, L]`` (the padding left out)."""
        return sampled[sampled[VALID]]

    def inputs(self, sampled: TensorDict, after: bool = False) -> SequenceInputs:
        """Each sensor's sequences ``[B, L, ...]``; ``after``: the first state, then the
        states after each step ``[B, L + 1, ...]``."""
        names = self.network.sensor_names
        if not after:
            return SequenceInputs([sampled[keys.OBS, name] for name in names], sampled)
        sensors = [
            torch.cat([sampled[keys.OBS, name][:, :1], sampled[keys.NEXT, keys.OBS, name]], dim=1)
            for name in names
        ]
        return SequenceInputs(sensors, sampled)

    def policy_params(self, inputs: SequenceInputs) -> tuple[torch.Tensor, ...]:
        """The actor from each sequence's stored memory; its real steps' params."""
        net, seqs = self.network, inputs.sequences
        b, n = inputs.sensors[0].shape[:2]
        sensors = zip(net.sensor_names, inputs.sensors, strict=True)
        encoded = net.encode({name: x.flatten(0, 1) for name, x in sensors})
        hidden = net.trunk(encoded).unflatten(0, (b, n))
        assert net.lstm is not None
        hidden = net.recur(net.lstm, hidden, seqs[keys.MEMORY][:, 0])[0]
        return self.policy.heads(hidden[:, inputs.skipped :][seqs[VALID]])

    def q_values(
        self, qs: nn.ModuleList, inputs: SequenceInputs, actions: list[torch.Tensor]
    ) -> torch.Tensor:
        """Both Qs over the sequences from zero memory ``[2, real steps, streams,
        outputs]``; a continuous ``actions`` (one per real step) is laid back along the
        sequences, after the stored first action when the inputs start a state earlier."""
        seqs = inputs.sequences
        valid = seqs[VALID]
        along: list[torch.Tensor] = []
        if actions:
            laid = actions[0].new_zeros(*valid.shape, actions[0].shape[-1])
            laid[valid] = actions[0]
            if inputs.skipped:
                laid = torch.cat([seqs[CONTINUOUS_ACTION][:, :1], laid], dim=1)
            along = [laid]
        out = torch.stack([q.sequences(*inputs.sensors, *along) for q in qs])
        return out[:, :, inputs.skipped :][:, valid].unflatten(-1, (self.streams, -1))
