"""PPO with memory (``network_settings.memory``), as mlagents-learn trains a recurrent policy.

What differs from ``learners/algorithms/ppo.py``, top to bottom:

- Workers act through the actor's LSTM and store, with each step, the memory its decision
  read (``rollout/collecting/segments.py``); the store keeps it (``Rows.memory``).
- The update cuts every stored trajectory piece into sequences of ``sequence_length``
  steps from its start, the last one padded at its end (``sequences``), as ML-Agents' buffer
  does.
- The critic has an LSTM of its own, whose memory no worker carries. As ML-Agents'
  ``_evaluate_by_sequence``, the update runs it along each agent's pieces in order,
  sequence by sequence, from the memory the agent's previous piece left (kept across
  updates by agent; zeros where the actor's memory is zeros, an episode's start). That
  gives each step's value, the bootstrap at a truncated end, and the critic's memory at
  each sequence's start.
- Minibatches are ``batch_size // sequence_length`` shuffled sequences. The actor runs
  from its stored memory at each sequence's start, the critic from the one just computed;
  the losses are ML-Agents' means over the sequences' real steps (padding left out).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict
from torch.nn.utils.rnn import pack_padded_sequence, pad_packed_sequence

from batches import keys
from learners.algorithms.minibatch import MinibatchStep
from learners.algorithms.ppo import PPO, Steps, policy_terms, value_chunk
from learners.networks.policies import lstm_state

if TYPE_CHECKING:
    from learners.algorithms.trajectory_store import Rows
    from learners.networks.policies import ActorCritic
    from learners.trainer_config.settings import TrainerSettings

CARRIED_AGENTS = 65_536  # critic memories kept between updates (agents mid-episode)


@dataclass(frozen=True)
class Sequences:
    """The update's steps as sequences: ``rows [S, L]`` (padding repeats a piece's last
    row), ``valid [S, L]``, and per sequence its piece and its place in the piece."""

    rows: torch.Tensor
    valid: torch.Tensor
    piece: torch.Tensor  # [S]
    chunk: torch.Tensor  # [S]
    starts: torch.Tensor  # [P] each piece's first row
    chunks: torch.Tensor  # [P] each piece's sequences

    def __len__(self) -> int:
        return len(self.rows)


@dataclass(frozen=True)
class SequenceInputs:
    """What the update's minibatches read besides ``PPO._bound``, fixed once the values are
    estimated: the sequences, the actor's and the critic's memory at each one's start
    ``[S, M]``, and which rows train ``[N]``."""

    sequences: Sequences
    actor_memory: torch.Tensor
    critic_memory: torch.Tensor
    train: torch.Tensor


def sequences(done: torch.Tensor, length: int) -> Sequences:
    """Cut the packed pieces (each ends at a ``done`` row) into sequences of ``length``."""
    ends = done.nonzero().squeeze(-1)
    starts = torch.cat([ends.new_zeros(1), ends[:-1] + 1])
    chunks = (ends - starts) // length + 1
    piece = torch.repeat_interleave(torch.arange(len(ends), device=done.device), chunks)
    first_of_piece = torch.cumsum(chunks, 0) - chunks
    chunk = torch.arange(len(piece), device=done.device) - first_of_piece[piece]
    rows = (starts[piece] + chunk * length).unsqueeze(-1) + torch.arange(length, device=done.device)
    last = ends[piece].unsqueeze(-1)
    return Sequences(rows.clamp(max=last), rows <= last, piece, chunk, starts, chunks)


class RecurrentPPO(PPO):
    def __init__(
        self, network: ActorCritic, settings: TrainerSettings, *args: Any, **kwargs: Any
    ) -> None:
        """As ``PPO``'s (``compute``, ``experts`` after the settings)."""
        super().__init__(network, settings, *args, **kwargs)
        memory = settings.network_settings.memory
        assert memory is not None and network.critic_lstm is not None
        self.length = memory.sequence_length
        self.step = MinibatchStep(
            self._minibatch_loss,
            self.optimizer,
            max(1, settings.hyperparameters.batch_size // self.length),
            self.compute,
            self.reported,
        )
        self.step.graphable = False  # a minibatch's real steps vary in number
        self.carried: OrderedDict[int, torch.Tensor] = OrderedDict()  # agent -> critic memory
        self._inputs: SequenceInputs | None = None  # this update's, as PPO's ``_bound``
        self.padding = 0  # the stored pieces' padding to whole sequences
        self.seen = [0, 0]  # steps and padding of every piece so far

    def add(self, segment: TensorDict, lag: torch.Tensor) -> int:
        """As ``PPO.add``; also counts the padding the segment's pieces will get."""
        steps = super().add(segment, lag)
        ends = segment[keys.NEXT, keys.DONE].reshape(-1).nonzero().squeeze(-1)
        lengths = torch.diff(ends, prepend=ends.new_full((1,), -1))
        padding = int((-lengths % self.length).sum())
        self.padding += padding
        self.seen = [self.seen[0] + len(segment), self.seen[1] + padding]
        return steps

    def buffered(self) -> int:
        """Steps and padding: ML-Agents' update buffer holds the sequences padded, and its
        trainer counts the padding towards ``buffer_size`` too."""
        return self.store.train_steps + self.padding

    def wanted(self) -> int | None:
        """The agent steps still missing: the buffer's places, less the share that
        padding has taken of the pieces so far (workers count steps)."""
        missing = super().wanted()
        assert missing is not None
        steps, padding = self.seen
        return max(1, math.ceil(missing * steps / (steps + padding))) if steps else missing

    def update(self, progress: float) -> dict[str, float]:
        self.padding = 0  # the store is taken whole
        return super().update(progress)

    # --- values along each agent's pieces ----------------------------------------------------

    def value_estimates(self, rows: Rows) -> tuple[torch.Tensor, torch.Tensor]:
        assert rows.memory is not None and rows.agent is not None
        seqs = sequences(rows.done, self.length)
        agents = rows.agent[seqs.starts].tolist()  # each piece's
        order, chain_of, begin = self._chains(rows, seqs, agents)
        position = order[seqs.piece] + seqs.chunk  # the sequence's place along its chain
        chain = chain_of[seqs.piece]
        memory = begin  # [chains, M]: each chain's critic memory now
        heads = 1 + len(self.signals)
        value = torch.zeros(len(rows), heads, device=rows.memory.device)
        critic_start = torch.zeros(len(seqs), memory.shape[1], device=memory.device)
        after_piece = torch.zeros(len(seqs.starts), memory.shape[1], device=memory.device)
        for k in range(int(position.max()) + 1 if len(seqs) else 0):
            for at in self._batches((position == k).nonzero().squeeze(-1), rows):
                critic_start[at] = memory[chain[at]]
                out, memory_after = self._critic_pass(rows, seqs, at, memory[chain[at]])
                valid = seqs.valid[at]
                value[seqs.rows[at][valid]] = out[valid]
                memory[chain[at]] = memory_after
                ends = at[seqs.chunk[at] == seqs.chunks[seqs.piece[at]] - 1]
                after_piece[seqs.piece[ends]] = memory[chain[ends]]
        self._remember(rows, seqs, agents, after_piece)
        next_value = torch.zeros_like(value)
        next_value[:-1] = value[1:]
        if len(rows.end_rows):
            piece = torch.searchsorted(seqs.starts, rows.end_rows, right=True) - 1
            next_value[rows.end_rows] = self._end_values(rows.end_obs, after_piece[piece])
        self._inputs = SequenceInputs(seqs, rows.memory[seqs.rows[:, 0]], critic_start, rows.train)
        return value, next_value

    def _chains(
        self, rows: Rows, seqs: Sequences, agents: list[int]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Link each piece to the same agent's previous one in this update (unless it starts
        an episode: the actor's memory all zeros): per piece, where its first sequence sits
        along its chain and the chain's number; per chain, the critic memory it starts from."""
        assert rows.memory is not None
        fresh = (rows.memory[seqs.starts] == 0).all(-1).tolist()
        chunks = seqs.chunks.tolist()
        size = rows.memory.shape[1]
        order, chain_of, begin, last = [], [], [], {}
        for p, (agent, new) in enumerate(zip(agents, fresh, strict=True)):
            before = None if new else last.get(agent)
            if before is None:
                carried = None if new else self.carried.pop(agent, None)
                begin.append(carried if carried is not None else rows.memory.new_zeros(size))
                chain_of.append(len(begin) - 1)
                order.append(0)
            else:
                chain_of.append(chain_of[before])
                order.append(order[before] + chunks[before])
            last[agent] = p
        device = rows.memory.device
        return (
            torch.tensor(order, device=device, dtype=torch.int64),
            torch.tensor(chain_of, device=device, dtype=torch.int64),
            torch.stack(begin) if begin else rows.memory.new_zeros(0, size),
        )

    def _remember(
        self, rows: Rows, seqs: Sequences, agents: list[int], after_piece: torch.Tensor
    ) -> None:
        """Keep each agent's critic memory after its last piece, for its next one, unless
        its episode ended there for good."""
        last_rows = torch.cat([seqs.starts[1:] - 1, seqs.starts.new_tensor([len(rows) - 1])])
        going_on = (~rows.terminated[last_rows]).tolist() if len(seqs.starts) else []
        for p, (agent, keep) in enumerate(zip(agents, going_on, strict=True)):
            self.carried.pop(agent, None)
            if keep:
                self.carried[agent] = after_piece[p]
        while len(self.carried) > CARRIED_AGENTS:
            self.carried.popitem(last=False)

    def _batches(self, at: torch.Tensor, rows: Rows) -> list[torch.Tensor]:
        """``at`` in parts whose observations stay within ``VALUE_CHUNK_BYTES`` as floats."""
        return list(at.split(value_chunk(rows.obs, self.length)))

    def _critic_pass(
        self, rows: Rows, seqs: Sequences, at: torch.Tensor, memory: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The critic along sequences ``at`` from ``memory``: values ``[s, L, heads]`` and
        the memory after each one's last real step."""
        net, places = self.network, seqs.rows[at]
        assert net.critic_lstm is not None
        encoded = net.encode({n: o[places.flatten()] for n, o in rows.obs.items()}, critic=True)
        critic = net.critic_trunk(encoded).unflatten(0, places.shape)
        start = lstm_state(memory, net.critic_lstm.hidden_size)
        lengths = seqs.valid[at].sum(-1).cpu()
        packed = pack_padded_sequence(critic, lengths, batch_first=True, enforce_sorted=False)
        out, (h, c) = net.critic_lstm(packed, start)
        out = pad_packed_sequence(out, batch_first=True, total_length=self.length)[0]
        values = net.value_head(out, self.signals.heads).reshape(*places.shape, -1)
        return values, torch.cat([h[0], c[0]], dim=-1)

    def _end_values(self, obs: dict[str, torch.Tensor], memory: torch.Tensor) -> torch.Tensor:
        """V of the kept next observations at truncated ends, one critic step further."""
        net = self.network
        assert net.critic_lstm is not None
        critic = net.critic_trunk(net.encode(obs, critic=True))
        out = net.recur(net.critic_lstm, critic, memory)[0]
        return net.value_head(out, self.signals.heads).reshape(len(memory), -1)

    # --- the update --------------------------------------------------------------------------

    def normalized(self, advantage: torch.Tensor, train: torch.Tensor) -> torch.Tensor:
        """As ML-Agents' ``_update_policy``: over its update buffer, where each sequence's
        padding holds advantage 0, so the padding counts in the mean and the std."""
        assert self._inputs is not None
        trained = advantage[train]
        count = len(trained) + int((~self._inputs.sequences.valid).sum())
        mean = trained.sum() / count
        std = (trained.square().sum() / count - mean.square()).clamp(min=0.0).sqrt()
        return (advantage - mean) / (std + 1e-10)

    def epochs(self, train: torch.Tensor) -> None:
        """``num_epoch`` passes over the sequences with a step to train, shuffled, in
        minibatches of ``batch_size // sequence_length`` (the remainder left out)."""
        assert self._inputs is not None
        seqs, trained, h = self._inputs.sequences, self._inputs.train, self.settings.hyperparameters
        kept = (trained[seqs.rows] & seqs.valid).any(-1).nonzero().squeeze(-1)
        count = len(self.step.index)
        for _ in range(h.num_epoch):
            order = kept[torch.randperm(len(kept), device=kept.device)]
            for index in order.split(count):
                if len(index) == count:
                    self.step(index)

    def _minibatch_loss(
        self, index: torch.Tensor, scalars: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        assert self._bound is not None and self._inputs is not None
        inputs, bound = self._inputs, self._bound
        places = inputs.sequences.rows[index]  # [B, L]
        real = inputs.sequences.valid[index] & inputs.train[places]
        memories = (inputs.actor_memory[index], inputs.critic_memory[index])
        log_prob, entropy, value = self.network.evaluate(
            {n: o[places] for n, o in bound.obs.items()},
            None if bound.continuous is None else bound.continuous[places],
            None if bound.discrete is None else bound.discrete[places],
            None if bound.mask is None else bound.mask[places],
            self.signals.heads,
            memories,
        )
        steps: Steps = bound[places[real]]
        terms = policy_terms(log_prob[real], entropy[real], steps, scalars[0], scalars[1])
        value_loss = (steps.value_target - value[real]).square()
        return {
            "loss_objective": terms.pop("loss_objective"),
            "loss_critic": 0.5 * value_loss.mean(),
        } | terms
