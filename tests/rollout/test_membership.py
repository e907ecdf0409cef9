"""Elastic membership's decisions (rollout/serving/membership.py), on a cluster size set by the
test: no Ray."""

from __future__ import annotations

import pytest

from rollout.serving import membership
from rollout.serving.membership import Membership


@pytest.fixture
def slots(monkeypatch):
    """The cluster's worker slots, as the test sets them."""
    size = {"slots": 4}
    monkeypatch.setattr(membership, "cluster_slots", lambda worker, learner: size["slots"])
    return size


def test_workers_are_added_up_to_the_clusters_slots_once_the_live_ones_delivered(slots):
    m = Membership(every_s=0.0)
    assert m.missing([0, 1]) == 0  # both still joining: the cluster's view may be stale
    m.delivered_by(0)
    m.delivered_by(1)
    assert m.missing([0, 1]) == 2
    slots["slots"] = 1  # a node left: nothing to add, and nothing removed by this count
    assert m.missing([0, 1]) == 0


def test_max_workers_caps_the_count(slots):
    m = Membership(max_workers=3, every_s=0.0)
    m.delivered_by(0)
    assert m.missing([0]) == 2


def test_the_cluster_is_read_at_most_every_every_s(slots):
    m = Membership(every_s=3600.0)
    m.delivered_by(0)
    assert m.missing([0]) == 3
    assert m.missing([0]) == 0  # read again only after every_s


def test_a_worker_that_delivered_leaves_without_failing_the_run():
    m = Membership(max_barren=1)
    for index in range(5):
        m.delivered_by(index)
        assert m.retire(index)
    assert m.removed == 5 and m.retired == set(range(5))


def test_workers_dying_before_their_first_collect_fail_the_run_after_max_barren():
    m = Membership(max_barren=2)
    assert m.retire(0) and m.retire(1)
    assert not m.retire(2)
    m.delivered_by(3)  # a delivery resets the count
    assert m.barren == 0


def test_cluster_slots_reads_the_clusters_cpus(ray_session):
    """The test session's Ray has 2 CPUs."""
    assert membership.cluster_slots(1.0, 1.0) == 1
    assert membership.cluster_slots(0.5, 0.0) == 4
    assert membership.cluster_slots(1.0, 4.0) == 1  # at least one
