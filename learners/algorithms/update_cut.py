"""Where an on-policy update falls within an arriving segment, so that it trains on the
steps mlagents-learn's would.

ML-Agents' trainer updates as soon as its buffer holds more than ``buffer_size`` steps,
with the trajectories that have arrived by then: those its environments finished up to the
step that tipped the buffer over. Trajectories finished later wait for the next buffer. A
segment here holds every trajectory a worker finished during one ``collect``, which spans
many exchanges when its agents are many or it collects ahead of the demand
(``rollout/serving/demand.py``). Stored whole, it made updates up to half again larger than
mlagents-learn's (Pyramids, 2 workers: 2,800-3,300 steps against 2,130), so fewer updates
per sample. The learner cuts it here instead; the rest waits for the next update.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from batches import keys

if TYPE_CHECKING:
    from tensordict import TensorDictBase


def update_cut(segment: TensorDictBase, wanted: int) -> int:
    """How many of ``segment``'s steps the update that ``wanted`` more steps make ready
    takes: the trajectories through the one that brings ``wanted``, and the others its
    worker finished in the same exchange (``ENV_STEPS``); all of them when it holds fewer."""
    count = segment.batch_size[0]
    if wanted >= count:
        return count
    ends = segment[keys.NEXT, keys.DONE].reshape(-1).nonzero().squeeze(-1)
    tipping = ends[ends >= wanted - 1]
    if not len(tipping):  # a segment always ends a trajectory; this only guards
        return count
    last = int(tipping[0])
    exchange = segment.get(keys.ENV_STEPS, None)
    if exchange is not None:  # the rows right after it, of the same exchange
        exchange = exchange.reshape(-1)
        later = ends[ends > last]
        same = int((exchange[later] == exchange[last]).int().cumprod(0).sum())
        if same:
            last = int(later[same - 1])
    return last + 1
