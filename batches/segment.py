"""The packed trajectories one worker hands the learner: plain numpy, no torch.

A :class:`Segment` is what travels (Ray's object store, the learner's queue); the learner
takes it ``to_tensordict``, the batch of docs/batch-format.md. ``rollout.collecting.segments``
builds them from Unity's steps. :class:`Sources` lets whoever takes them (a learner, a
queue) take a delivery Ray retried once.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from batches import keys

if TYPE_CHECKING:
    from tensordict import TensorDict


@dataclass(frozen=True)
class Segment:
    """One behavior's packed trajectories on their way from a worker to the learner: numpy
    arrays ``[N, ...]`` under the keys of docs/batch-format.md, nested as the learner's
    TensorDict will be, with the behavior's name and spec. The rollout side needs no torch:
    importing torch, tensordict and torchrl was most of a worker's start (3 s of 3.5 on 2
    cores) and of its memory. The learner takes it ``to_tensordict``."""

    behavior: str
    spec: dict[str, Any]  # specs.spec_to_dict
    data: Mapping[str, Any]  # key -> array, or -> a mapping of the same kind
    # (worker incarnation, collect number): the learner takes each source once, although
    # Ray may deliver a task's result twice (retries)
    source: tuple[str, int] | None = None

    def __len__(self) -> int:
        return len(self.data[keys.POLICY_VERSION])

    @property
    def nbytes(self) -> int:
        sizes: list[int] = []
        _walk(lambda a: sizes.append(a.nbytes) or a, self.data)
        return sum(sizes)

    def to_tensordict(self) -> TensorDict:
        """The learner's view: tensors sharing the arrays' memory (a copy only where Ray's
        object store handed over read-only arrays), behavior and spec as non-tensors."""
        import torch
        from tensordict import TensorDict

        def tensor(array: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.require(array, requirements="W"))

        batch = TensorDict(_walk(tensor, self.data), batch_size=[len(self)])
        batch.set_non_tensor(keys.BEHAVIOR, self.behavior)
        batch.set_non_tensor(keys.SPEC, self.spec)
        return batch

    @staticmethod
    def concat(parts: Sequence[Segment]) -> Segment:
        """Segments of one behavior, one after the other; groupmate places (``[N, M,
        ...]``, M grows during a run) are padded with empty ones to the widest."""
        if len(parts) == 1:
            return parts[0]

        def join(*arrays: np.ndarray) -> np.ndarray:
            widest = tuple(max(sizes) for sizes in zip(*(a.shape[1:] for a in arrays), strict=True))
            return np.concatenate([_padded(a, widest) for a in arrays])

        first = parts[0]
        data = _walk(join, *(p.data for p in parts))
        return Segment(first.behavior, first.spec, data, first.source)


def _padded(array: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``array [N, ...]`` zero-padded at the end of each later dimension to ``shape``."""
    if array.shape[1:] == shape:
        return array
    return np.pad(
        array, [(0, 0)] + [(0, w - s) for s, w in zip(array.shape[1:], shape, strict=True)]
    )


def _walk(fn: Callable[..., Any], *trees: Mapping[str, Any]) -> dict[str, Any]:
    """``fn`` on the arrays at the same place in nested mappings of the same shape."""
    return {
        key: _walk(fn, *(t[key] for t in trees))
        if isinstance(value, Mapping)
        else fn(*(t[key] for t in trees))
        for key, value in trees[0].items()
    }


class Sources:
    """The segment sources taken so far, to take each once. Per (incarnation, behavior): the
    number up to which all were taken, and those taken above it (deliveries come nearly in
    order, so the set stays small however long the run)."""

    def __init__(self) -> None:
        self._taken: dict[tuple[str, str], tuple[int, set[int]]] = {}

    def first(self, segment: Segment) -> bool:
        """Whether this is the first delivery of the segment's source (recording it)."""
        assert segment.source is not None
        incarnation, number = segment.source
        key = (incarnation, segment.behavior)
        upto, above = self._taken.get(key, (0, set()))
        if number <= upto or number in above:
            return False
        above.add(number)
        while upto + 1 in above:
            upto += 1
            above.discard(upto)
        self._taken[key] = (upto, above)
        return True
