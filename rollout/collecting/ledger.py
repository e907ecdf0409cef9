"""The sample ledger: for each worker and behavior, agent steps produced = delivered to the
learner + dropped, and every drop has a reason.

A worker's collector counts what it recorded (``Counts``) and sends the counts with every
collect (``Collected``). The service books, per worker incarnation and behavior, what
arrived, what the learner took, and what was lost on the way:

- ``player failure``: rows in progress when a Unity player crashed or hung;
- ``worker death``: rows in progress in a worker that died (as of its last collect);
- ``learner restart``: steps in flight to a learner that died, or acted with its weights;
- ``shutdown``: rows in progress, and data not yet taken, when the run stopped;
- ``lesson reset``: rows in progress when a curriculum lesson with ``require_reset``
  reset Unity (as mlagents-learn, which also drops them).

Steps a worker recorded after its last collect and before it died are in no count: the
ledger is exact as of each incarnation's last word.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

PLAYER_FAILURE = "player failure"
WORKER_DEATH = "worker death"
LEARNER_RESTART = "learner restart"
SHUTDOWN = "shutdown"
LESSON_RESET = "lesson reset"
REASONS = (PLAYER_FAILURE, WORKER_DEATH, LEARNER_RESTART, SHUTDOWN, LESSON_RESET)


@dataclass(frozen=True)
class Counts:
    """One behavior in one collector: ``produced == emitted + lost + reset + in_progress``."""

    produced: int = 0  # transitions recorded
    emitted: int = 0  # in rows handed out in segments
    lost: int = 0  # in rows thrown away when the player failed
    in_progress: int = 0  # in rows not finished yet
    reset: int = 0  # in rows thrown away when a lesson reset Unity


class Collected(list):  # a list: the learner takes it as its segments
    """A collect's segments, with its worker's counts after it (behavior -> Counts)."""

    def __init__(self, segments: Any, incarnation: str, counts: dict[str, Counts]) -> None:
        super().__init__(segments)
        self.incarnation = incarnation
        self.counts = counts


def steps_of(segments: list) -> dict[str, int]:
    """Steps per behavior in one collect's segments."""
    steps: dict[str, int] = {}
    for segment in segments:
        steps[segment.behavior] = steps.get(segment.behavior, 0) + len(segment)
    return steps


@dataclass
class Entry:
    produced: int = 0
    delivered: int = 0
    dropped: Counter[str] = field(default_factory=Counter)

    def balanced(self) -> bool:
        return self.produced == self.delivered + sum(self.dropped.values())


class Ledger:
    """Booked by the service; ``summary()`` goes to summary.json."""

    def __init__(self) -> None:
        self._counts: dict[tuple[int, str], dict[str, Counts]] = {}  # last word
        self._entries: dict[tuple[int, str, str], Entry] = {}
        self._current: dict[int, str] = {}  # worker index -> its live incarnation
        self._closed: set[str] = set()

    def _entry(self, index: int, incarnation: str, behavior: str) -> Entry:
        return self._entries.setdefault((index, incarnation, behavior), Entry())

    def arrived(self, index: int, collected: Collected) -> bool:
        """A collect came back: its worker's counts, as of now. True when it comes from a
        new incarnation no failure announced (Ray restarted the worker unseen)."""
        previous = self._current.get(index)
        unseen = previous is not None and previous != collected.incarnation
        if unseen:
            self.ended(index, WORKER_DEATH)  # Ray restarted it without our seeing
        self._current[index] = collected.incarnation
        self._counts[(index, collected.incarnation)] = collected.counts
        return unseen

    def book(self, index: int, incarnation: str, steps: dict[str, int], how: str) -> None:
        """Steps of arrived segments, per behavior: ``delivered`` or a drop reason."""
        for behavior, n in steps.items():
            entry = self._entry(index, incarnation, behavior)
            if how == "delivered":
                entry.delivered += n
            else:
                entry.dropped[how] += n

    def ended(self, index: int, reason: str, final: Collected | None = None) -> None:
        """The worker's incarnation is over: what it had in progress is dropped."""
        incarnation = self._current.pop(index, None)
        if final is not None:
            incarnation = final.incarnation
            self._counts[(index, incarnation)] = final.counts
        if incarnation is None or incarnation in self._closed:
            return
        self._closed.add(incarnation)
        for behavior, counts in self._counts.get((index, incarnation), {}).items():
            entry = self._entry(index, incarnation, behavior)
            entry.dropped[reason] += counts.in_progress

    def _rows(self) -> dict[tuple[int, str, str], Entry]:
        """Every (worker index, incarnation, behavior): what the service booked, with what
        the worker's last counts say it produced and lost to player failures."""
        rows = {key: Entry(0, e.delivered, Counter(e.dropped)) for key, e in self._entries.items()}
        for (index, incarnation), counts in self._counts.items():
            for behavior, c in counts.items():
                row = rows.setdefault((index, incarnation, behavior), Entry())
                row.produced = c.produced
                row.dropped[PLAYER_FAILURE] = c.lost
                row.dropped[LESSON_RESET] = c.reset
        return rows

    def summary(self) -> dict[str, Any]:
        """Per worker index and behavior (incarnations added up), totals, and whether every
        closed incarnation balances exactly."""
        rows = self._rows()
        workers: dict[str, dict[str, dict[str, Any]]] = {}
        total = Entry()
        for (index, _, behavior), entry in sorted(rows.items()):
            row = workers.setdefault(str(index), {}).setdefault(
                behavior, {"produced": 0, "delivered": 0, "dropped": dict.fromkeys(REASONS, 0)}
            )
            row["produced"] += entry.produced
            row["delivered"] += entry.delivered
            for reason, n in entry.dropped.items():
                row["dropped"][reason] += n
            total.produced += entry.produced
            total.delivered += entry.delivered
            total.dropped.update(entry.dropped)
        closed = [e for (_, inc, _), e in rows.items() if inc in self._closed]
        return {
            "workers": workers,
            "produced": total.produced,
            "delivered": total.delivered,
            "dropped": {reason: total.dropped[reason] for reason in REASONS},
            "balanced": all(e.balanced() for e in closed) and len(closed) == len(rows),
        }

    def dropped_by_reason(self) -> dict[str, int]:
        """Steps dropped so far, per reason (the live table; cheaper than ``summary``)."""
        dropped = Counter({PLAYER_FAILURE: 0})
        for entry in self._entries.values():
            dropped.update(entry.dropped)
        every = [c for counts in self._counts.values() for c in counts.values()]
        dropped[PLAYER_FAILURE] = sum(c.lost for c in every)
        dropped[LESSON_RESET] = sum(c.reset for c in every)
        return {reason: dropped[reason] for reason in REASONS}
