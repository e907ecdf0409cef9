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


class RecurrentSAC(SAC):
    q_network = RecurrentQNetwork

    def __init__(
        self, network: ActorCritic, settings: TrainerSettings, *args: Any, **kwargs: Any
    ) -> None:
        """As ``SAC``'s (``compute``, ``experts`` after the settings)."""
        memory = settings.network_settings.memory
        assert memory is not None and network.lstm is not None
        self.length = memory.sequence_length
        self._sequences: TensorDict | None = None  # the gradient step's, [B, L]
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

    def sample(self) -> TensorDict:
        """The real steps of sampled sequences (what the signals train on)."""
        sampled = self.buffer.sample()
        return sampled[sampled[VALID]]

    def gradient_step(self, batch: TensorDict) -> dict[str, torch.Tensor]:
        """SAC's step on the real steps of sampled sequences ``[B, L]``; the networks run
        over the whole sequences (``policy_params``, ``q_values``)."""
        self._sequences = batch
        try:
            return super().gradient_step(batch[batch[VALID]])
        finally:
            self._sequences = None

    def inputs(self, batch: TensorDict, after: bool = False) -> Any:
        """Each sensor's sequences ``[B, L, ...]``; ``after``: the first state, then the
        states after each step ``[B, L + 1, ...]``."""
        seqs = self._sequences
        assert seqs is not None
        if not after:
            return [seqs[keys.OBS, name] for name in self.network.sensor_names]
        return [
            torch.cat([seqs[keys.OBS, name][:, :1], seqs[keys.NEXT, keys.OBS, name]], dim=1)
            for name in self.network.sensor_names
        ]

    def policy_params(self, inputs: Any) -> tuple[torch.Tensor, ...]:
        """The actor from each sequence's stored memory; its real steps' params."""
        seqs = self._sequences
        assert seqs is not None
        net = self.network
        b, n = inputs[0].shape[:2]
        sensors = zip(net.sensor_names, inputs, strict=True)
        encoded = net.encode({name: x.flatten(0, 1) for name, x in sensors})
        hidden = net.trunk(encoded).unflatten(0, (b, n))
        assert net.lstm is not None
        hidden = net.recur(net.lstm, hidden, seqs[keys.MEMORY][:, 0])[0]
        return self.policy.heads(hidden[:, n - self.length :][seqs[VALID]])

    def q_values(self, qs: nn.ModuleList, inputs: Any, actions: list[torch.Tensor]) -> torch.Tensor:
        """Both Qs over the sequences from zero memory ``[2, real steps, streams,
        outputs]``; a continuous ``actions`` (one per real step) is laid back along the
        sequences, after the stored first action when the inputs start a state earlier."""
        seqs = self._sequences
        assert seqs is not None
        valid = seqs[VALID]
        n = inputs[0].shape[1]
        along: list[torch.Tensor] = []
        if actions:
            laid = actions[0].new_zeros(*valid.shape, actions[0].shape[-1])
            laid[valid] = actions[0]
            if n > self.length:
                laid = torch.cat([seqs[CONTINUOUS_ACTION][:, :1], laid], dim=1)
            along = [laid]
        out = torch.stack([q.sequences(*inputs, *along) for q in qs])
        return out[:, :, n - self.length :][:, valid].unflatten(-1, (self.streams, -1))
