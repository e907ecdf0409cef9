"""The sample ledger's books (rollout.collecting.ledger), without Ray: produced = delivered +
dropped, each drop with its reason, across a worker's restart, a lesson's reset and the run's
end."""

from __future__ import annotations

from rollout.collecting.ledger import (
    LEARNER_RESTART,
    LESSON_RESET,
    PLAYER_FAILURE,
    SHUTDOWN,
    WORKER_DEATH,
    Collected,
    Counts,
    Ledger,
)


def collected(
    incarnation: str, produced: int, emitted: int, lost: int = 0, reset: int = 0
) -> Collected:
    counts = Counts(produced, emitted, lost, produced - emitted - lost - reset, reset)
    return Collected([], incarnation, {"B?team=0": counts})


def test_the_books_balance_through_a_restart_a_dead_learner_and_the_end():
    ledger = Ledger()
    ledger.arrived(0, collected("a", 100, 60, lost=10))  # 30 in progress
    ledger.book(0, "a", {"B?team=0": 40}, "delivered")
    ledger.book(0, "a", {"B?team=0": 20}, LEARNER_RESTART)  # in flight when it died
    ledger.ended(0, WORKER_DEATH)  # killed: its 30 in progress are lost with it
    ledger.arrived(0, collected("b", 50, 50))  # Ray's restart of worker 0
    ledger.book(0, "b", {"B?team=0": 50}, "delivered")
    ledger.arrived(1, collected("c", 80, 70))
    ledger.book(1, "c", {"B?team=0": 70}, SHUTDOWN)  # collected, never taken
    ledger.ended(1, SHUTDOWN, collected("c", 85, 70, reset=5))  # 10 in progress at close
    ledger.ended(0, SHUTDOWN, collected("b", 50, 50))
    summary = ledger.summary()
    assert summary["balanced"]
    assert summary["produced"] == 100 + 50 + 85
    assert summary["delivered"] == 90
    assert summary["dropped"] == {
        PLAYER_FAILURE: 10,
        WORKER_DEATH: 30,
        LEARNER_RESTART: 20,
        SHUTDOWN: 80,
        LESSON_RESET: 5,  # rows in progress when a lesson with require_reset reset Unity
    }
    assert summary["workers"]["0"]["B?team=0"]["produced"] == 150
    assert ledger.dropped_by_reason() == summary["dropped"]  # the live table's view
    assert sum(ledger.dropped_by_reason().values()) == 145


def test_a_lost_delivery_unbalances_the_books():
    ledger = Ledger()
    ledger.arrived(0, collected("a", 100, 100))
    ledger.book(0, "a", {"B?team=0": 90}, "delivered")  # 10 went nowhere
    ledger.ended(0, SHUTDOWN, collected("a", 100, 100))
    assert not ledger.summary()["balanced"]


def test_a_restart_seen_only_through_a_new_incarnation_closes_the_old_one():
    ledger = Ledger()
    assert not ledger.arrived(0, collected("a", 10, 4))
    ledger.book(0, "a", {"B?team=0": 4}, "delivered")
    # no death seen: the new incarnation says so (and the service counts the restart)
    assert ledger.arrived(0, collected("b", 3, 0))
    ledger.ended(0, SHUTDOWN, collected("b", 3, 0))
    summary = ledger.summary()
    assert summary["balanced"] and summary["dropped"][WORKER_DEATH] == 6
