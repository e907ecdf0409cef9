"""How many steps the service sends workers after: the learner's demand, and when the
workers' own rows make waiting for its weights pointless.

An on-policy learner (PPO) answers each submission with the steps it still misses before
its next update. Once the steps on their way cover that, idle workers wait for the new
weights, as mlagents-learn's environments wait for each update, so that the update's
buffer holds steps of the policy it improves.

That holds only while the workers' rows in progress are smaller than a buffer. A row is
delivered whole once its agent has acted ``time_horizon`` steps (or its episode ended);
when the rows the workers hold together are longer than a buffer (many workers, many
agents, long horizons), a row is acted across several updates whatever the workers do,
and waiting only idles them: every buffer already holds steps acted by older weights. So
the service sends workers after the demand plus what their rows hold beyond a buffer
(``rows_beyond_buffer``): with 16 workers of 12 agents and rows of 64 steps, about
12,000 steps in rows against a buffer of 2,400, they then collect through each update;
with 2 workers, 1,500 steps in rows, they wait for it as before. ``collect_ahead`` (the
CLI's ``--collect-ahead``) adds a fixed number of steps on top.

The rows counted are every behavior's a worker holds, and the buffer is the least one the
learner states (its demand is its behaviors' least): with a self-play opponent's rows, or an
off-policy behavior's beside an on-policy one, the excess is an upper bound, and workers go
on a little further than the on-policy behavior alone would warrant. Before the learner's
first update its largest demand is below a buffer, so the excess is larger then too.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping

from rollout.collecting.ledger import Counts


class Demand:
    """The learner's last demand, its largest (its buffer), and each worker's rows."""

    def __init__(self) -> None:
        self.wanted: int | None = None  # the learner's last answer: steps before its update
        self.buffer = 0  # the largest demand stated: what the learner asks right after an update
        self._rows: dict[int, int] = {}  # worker -> the most steps it held in unfinished rows

    def answered(self, wanted: int | None) -> None:
        self.wanted = wanted
        if wanted is not None:
            self.buffer = max(self.buffer, wanted)

    def rows_seen(self, worker: int, counts: Mapping[str, Counts]) -> None:
        """A collect came back with its worker's counts: its rows in progress, every behavior's."""
        held = sum(c.in_progress for c in counts.values())
        self._rows[worker] = max(self._rows.get(worker, 0), held)

    def rows(self, live: Collection[int]) -> int:
        """The most steps the live workers have held in rows in progress, together."""
        return sum(self._rows.get(worker, 0) for worker in live)

    def rows_beyond_buffer(self, live: Collection[int]) -> int:
        """Steps the live workers' rows hold beyond one buffer (0 while they hold less)."""
        return max(0, self.rows(live) - self.buffer)

    def missing(self, coming: int, live: Collection[int], ahead: int) -> int:
        """Steps to send idle workers after, beyond ``coming`` (those on their way)."""
        assert self.wanted is not None
        return self.wanted + self.rows_beyond_buffer(live) + ahead - coming


def share(missing: int, idle: int, shortest_row: int) -> int:
    """Each idle worker's part of ``missing``: at least a row's worth, since rows arrive
    whole and a smaller ask only adds round trips."""
    return max(math.ceil(missing / idle), shortest_row)
