"""An on-policy learner's steps, written once, at ingestion, into tensors on its device.

Segments arrive as packed trajectories (docs/batch-format.md). Each field goes straight
into a preallocated tensor on the learner's device, in the dtype it came in (cameras stay
uint8), so an update neither concatenates the buffer nor copies it. The tensors hold
``rows`` (``buffer_size``) plus room past it: the update comes once the buffer is *over*
``buffer_size``, with the trajectory that tipped it over and the others its worker finished
in the same exchange (the learner cuts segments there, ``learners/algorithms/update_cut.py``).

Observations are kept once. Within a trajectory the next observation of a step is the
observation of the step after it, so ``("next", "obs")`` is kept only where a trajectory
ends without ``terminated`` (a horizon cut, MaxStep): there the estimator bootstraps from
it. A terminated end bootstraps with 0 and needs none, unless an intrinsic signal reads
it (``terminal_obs``). ML-Agents' buffer keeps one copy too.

The reward kept is the extrinsic signal's (``learners/reward_signals/extrinsic.py``: the group
reward added). With ``groupmates`` (POCA) the store also keeps each step's groupmates
(``rollout.collecting.groups``), and an agent's end counts as terminated only when every groupmate's
episode ended too, as ML-Agents' POCA decides: an agent that leaves its group mid-episode bootstraps
from the group's next observations, which are kept at such ends. Groupmate places (``M``) are padded
to the most any segment brought.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from batches import keys
from learners.host.devices import free_memory
from learners.reward_signals.episode_sums import agent_key, episode_ended
from learners.reward_signals.extrinsic import extrinsic_reward

if TYPE_CHECKING:
    from tensordict import TensorDictBase

# what an update takes beyond the store: value chunks, a minibatch's activations, gradients
UPDATE_HEADROOM = 512 * 2**20


class BufferTooLarge(MemoryError):
    """The configured buffer cannot fit the learner's memory; one line with the figures."""


@dataclass(frozen=True)
class Rows:
    """The stored steps of one update, views ``[n, ...]`` of the store's tensors."""

    obs: dict[str, torch.Tensor]
    continuous: torch.Tensor | None
    discrete: torch.Tensor | None
    mask: torch.Tensor | None  # True = allowed
    log_prob: torch.Tensor  # [n, components]
    reward: torch.Tensor  # [n]
    done: torch.Tensor  # [n] bool
    terminated: torch.Tensor  # [n] bool
    train: torch.Tensor  # [n] bool: counts in the loss (else context for the estimator)
    end_rows: torch.Tensor  # [e] int64: the ends that bootstrap, in row order
    end_obs: dict[str, torch.Tensor]  # [e, ...]: their next observations
    # a recurrent policy's only: the memory each step's decision read [n, memory_size]
    memory: torch.Tensor | None = None
    # a recurrent policy's and a store's with ``episodes``: the agent (worker and Unity id
    # in one int64) [n]; the latter's also where an episode ended (not a cut) [n] bool
    agent: torch.Tensor | None = None
    ended: torch.Tensor | None = None
    # groupmates only: "obs/<sensor>" [n, M, ...], "continuous", "discrete", "present",
    # "reward" [n, M]; at the ends "obs/<sensor>" and "present"
    groupmates: dict[str, torch.Tensor] = field(default_factory=dict)
    end_groupmates: dict[str, torch.Tensor] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.log_prob)


class TrajectoryStore:
    """Preallocated columns; ``add`` appends a segment, ``take`` hands all rows over."""

    def __init__(
        self,
        buffer_size: int,
        device: torch.device | str = "cpu",
        groupmates: bool = False,
        terminal_obs: bool = False,
        episodes: bool = False,
    ) -> None:
        """``terminal_obs``: keep the next observation at terminated ends too (intrinsic
        signals bootstrap there and read it). ``episodes``: keep each step's agent and
        whether its episode ended there (per-episode sums, as ML-Agents reports them)."""
        self.buffer_size = buffer_size
        self.terminal_obs = terminal_obs
        self.episodes = episodes
        self.device = torch.device(device)
        self.groupmates = groupmates
        self.places = 0  # groupmate places kept per step
        self.columns: dict[str, torch.Tensor] = {}
        self.ends: dict[str, torch.Tensor] = {}
        self.rows = 0  # rows stored
        self.end_count = 0
        self.train_steps = 0  # rows that count in the loss

    def add(self, segment: TensorDictBase, keep: torch.Tensor | None = None) -> int:
        """Store a packed segment; ``keep`` (per step) narrows which steps train."""
        count = segment.batch_size[0]
        if keep is None:  # every step, on the segment's device (not torch's default)
            keep = torch.ones_like(segment[keys.NEXT, keys.DONE].reshape(-1), dtype=torch.bool)
        fields = self._fields(segment, keep)
        kept = fields["done"] if self.terminal_obs else fields["done"] & ~fields["terminated"]
        ends = kept.nonzero().squeeze(-1)
        next_obs = {"obs/" + n: v[ends] for n, v in segment[keys.NEXT, keys.OBS].items()}
        if self.groupmates:
            after = segment[keys.NEXT, keys.GROUPMATES, keys.OBS]
            next_obs |= {"mate_obs/" + n: v[ends] for n, v in after.items()}
            next_obs["mate_present"] = fields["mate_present"][ends]
            next_obs = self._fit_places(fields, next_obs)
        if not self.columns:
            self._allocate(fields, next_obs, self.buffer_size + min(4 * count, self.buffer_size))
        self._fit(self.rows + count, self.end_count + len(ends))
        for name, value in fields.items():
            self.columns[name][self.rows : self.rows + count].copy_(value, non_blocking=True)
        end_rows = ends.to(self.device) + self.rows
        self.ends["row"][self.end_count : self.end_count + len(ends)] = end_rows
        for name, value in next_obs.items():
            column = self.ends[name]
            column[self.end_count : self.end_count + len(ends)].copy_(value, non_blocking=True)
        self.rows += count
        self.end_count += len(ends)
        steps = int(keep.sum())
        self.train_steps += steps
        return steps

    def take(self) -> Rows:
        """Every stored row (views, valid until the next ``add``); the store starts over."""
        rows = self._rows(self.rows, self.end_count)
        self.rows = self.end_count = self.train_steps = 0
        return rows

    def whole(self) -> Rows:
        """The columns at their full capacity, whatever is stored: a CUDA graph reads rows
        of them by index (``learners/algorithms/minibatch.py``), and their addresses stay put."""
        return self._rows(len(self.columns["log_prob"]), len(self.ends["row"]))

    def _rows(self, n: int, e: int) -> Rows:
        def column(name: str) -> torch.Tensor | None:  # an optional field
            return self.columns[name][:n] if name in self.columns else None

        obs = {k[4:]: v[:n] for k, v in self.columns.items() if k.startswith("obs/")}
        end_obs = {k[4:]: v[:e] for k, v in self.ends.items() if k.startswith("obs/")}
        mates = {k[5:]: v[:n] for k, v in self.columns.items() if k.startswith("mate_")}
        end_mates = {k[5:]: v[:e] for k, v in self.ends.items() if k.startswith("mate_")}
        return Rows(
            obs=obs,
            continuous=column("continuous"),
            discrete=column("discrete"),
            mask=column("mask"),
            log_prob=self.columns["log_prob"][:n],
            reward=self.columns["reward"][:n],
            done=self.columns["done"][:n],
            terminated=self.columns["terminated"][:n],
            train=self.columns["train"][:n],
            end_rows=self.ends["row"][:e],
            end_obs=end_obs,
            groupmates=mates,
            end_groupmates=end_mates,
            memory=column("memory"),
            agent=column("agent"),
            ended=column("ended"),
        )

    def nbytes(self) -> int:
        return sum(t.nbytes for t in (*self.columns.values(), *self.ends.values()))

    # --- internals ----------------------------------------------------------------------

    def _fields(self, segment: TensorDictBase, keep: torch.Tensor) -> dict[str, torch.Tensor]:
        fields = {"obs/" + name: value for name, value in segment[keys.OBS].items()}
        action = segment[keys.ACTION]
        optional = {
            keys.CONTINUOUS: action.get(keys.CONTINUOUS, None),
            keys.DISCRETE: action.get(keys.DISCRETE, None),
            "mask": segment.get(keys.ACTION_MASK, None),
        }
        fields.update({name: value for name, value in optional.items() if value is not None})
        fields["log_prob"] = segment[keys.LOG_PROB]
        fields["reward"] = extrinsic_reward(segment).reshape(-1)
        fields["done"] = segment[keys.NEXT, keys.DONE].reshape(-1)
        fields["terminated"] = segment[keys.NEXT, keys.TERMINATED].reshape(-1)
        fields["train"] = keep.to(torch.bool)
        if (memory := segment.get(keys.MEMORY, None)) is not None:
            fields["memory"] = memory
        if memory is not None or self.episodes:
            fields["agent"] = agent_key(segment)
        if self.episodes:
            fields["ended"] = episode_ended(segment)
        if self.groupmates:
            mates = segment[keys.GROUPMATES]
            fields |= {"mate_obs/" + n: v for n, v in mates[keys.OBS].items()}
            mate_action = mates[keys.ACTION]
            for name in (keys.CONTINUOUS, keys.DISCRETE):
                if (value := mate_action.get(name, None)) is not None:
                    fields["mate_" + name] = value
            fields["mate_present"] = mates[keys.PRESENT]
            fields["mate_reward"] = mates[keys.REWARD]
            # the group goes on while any groupmate's episode does: bootstrap from it
            going_on = (mates[keys.PRESENT] & ~mates[keys.DONE]).any(-1)
            fields["terminated"] = fields["terminated"] & ~going_on
        return fields

    def _fit_places(
        self, fields: dict[str, torch.Tensor], ends: dict[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        """Pad this segment's groupmate places to the store's, or widen the store's."""
        places = fields["mate_present"].shape[1]
        if places > self.places and self.columns:
            self.columns = {k: _widened(k, v, places) for k, v in self.columns.items()}
            self.ends = {k: _widened(k, v, places) for k, v in self.ends.items()}
        self.places = max(self.places, places)
        for tree in (fields, ends):
            for name, value in tree.items():
                tree[name] = _widened(name, value, self.places)
        return ends

    def _allocate(
        self, fields: dict[str, torch.Tensor], next_obs: dict[str, torch.Tensor], rows: int
    ) -> None:
        end_capacity = max(64, rows // 16)
        step = sum(_row_bytes(v) for v in fields.values())
        need = rows * step + end_capacity * sum(_row_bytes(v) for v in next_obs.values())
        free = free_memory(self.device)
        if free is not None and need + UPDATE_HEADROOM > free:
            raise BufferTooLarge(
                f"buffer_size {self.buffer_size} needs about {_gb(need + UPDATE_HEADROOM)} of "
                f"learner memory ({step:,} bytes per step, observations kept once, and "
                f"{_gb(UPDATE_HEADROOM)} for the update), and the learner's {self.device} has "
                f"{_gb(free)} free: lower buffer_size, or give the learner more memory"
            )
        for name, value in fields.items():
            self.columns[name] = self._empty(rows, value)
        self.ends["row"] = torch.empty(end_capacity, dtype=torch.int64, device=self.device)
        for name, value in next_obs.items():
            self.ends[name] = self._empty(end_capacity, value)

    def _empty(self, rows: int, like: torch.Tensor) -> torch.Tensor:
        return torch.empty((rows, *like.shape[1:]), dtype=like.dtype, device=self.device)

    def _fit(self, rows: int, ends: int) -> None:
        """Grow where a segment does not fit (once the buffer is past ``buffer_size``, the
        exchange that tips it over may bring many trajectories)."""
        if rows > len(self.columns["log_prob"]):
            size = max(rows, math.ceil(len(self.columns["log_prob"]) * 1.25))
            self.columns = {k: _grown(v, size, self.rows) for k, v in self.columns.items()}
        if ends > len(self.ends["row"]):
            size = max(ends, len(self.ends["row"]) * 2)
            self.ends = {k: _grown(v, size, self.end_count) for k, v in self.ends.items()}


def _grown(tensor: torch.Tensor, rows: int, used: int) -> torch.Tensor:
    bigger = torch.empty((rows, *tensor.shape[1:]), dtype=tensor.dtype, device=tensor.device)
    bigger[:used] = tensor[:used]
    return bigger


def _widened(name: str, tensor: torch.Tensor, places: int) -> torch.Tensor:
    """A groupmate column (``mate_*``, ``[n, M, ...]``) zero-padded to ``places``."""
    if not name.startswith("mate_") or tensor.shape[1] == places:
        return tensor
    pad = [0, 0] * (tensor.dim() - 2) + [0, places - tensor.shape[1]]
    return torch.nn.functional.pad(tensor, pad)


def _row_bytes(tensor: torch.Tensor) -> int:
    """Bytes of one row, also of a tensor with none (a segment without a truncated end)."""
    return math.prod(tensor.shape[1:]) * tensor.element_size()


def _gb(count: int) -> str:
    return f"{count / 2**30:.1f} GB"
