"""How the service sizes collects against an on-policy learner's demand (``_pump``,
``rollout/serving/demand.py``), with stand-in worker handles that record what they were asked: no
Ray, no Unity."""

from __future__ import annotations

import pytest

from learners.acting.factory import actor_factory
from rollout.collecting.ledger import Counts
from rollout.environment.unity import UnityConfig
from rollout.serving.demand import Demand
from rollout.serving.service import RolloutService, ServiceConfig


class _Collect:
    def __init__(self, asked: list[int]) -> None:
        self.asked = asked

    def remote(
        self, version: int, weights: object, steps: int, max_seconds: float, parameters: object
    ) -> object:
        self.asked.append(steps)
        return object()  # stands in for the call's ObjectRef


class _Worker:
    def __init__(self) -> None:
        self.asked: list[int] = []
        self.collect = _Collect(self.asked)


def pump(
    wanted: int | None,
    ahead: int = 0,
    idle: int = 4,
    in_flight: int = 0,
    horizon: int = 64,
    buffer: int | None = None,
    rows: int = 0,
) -> list[list[int]]:
    """What each of 4 workers is asked, ``idle`` of them idle, one collect of ``in_flight``
    steps already under way; ``buffer``: the learner's demand right after an update (as
    ``wanted`` when not given); ``rows``: the steps each worker has held in rows at most."""
    config = ServiceConfig(UnityConfig(None), num_workers=4, horizon=horizon, collect_ahead=ahead)
    service = RolloutService(config, actor_factory, learner=None)
    workers = [_Worker() for _ in range(4)]
    service.workers = workers
    service._worker_version = [0] * 4
    service._idle = set(range(idle))
    if buffer is not None:
        service.demand.answered(buffer)
    service.demand.answered(wanted)
    for worker in range(4):
        service.demand.rows_seen(worker, {"B": Counts(in_progress=rows)})
    if in_flight:
        service._collects[object()] = (3, in_flight)
    service._pump()
    return [w.asked for w in workers]


def test_the_demand_is_shared_among_idle_workers():
    assert pump(1000) == [[250]] * 4


def test_without_demand_every_idle_worker_collects_its_usual_size():
    assert pump(None, idle=2) == [[512], [512], [], []]


def test_steps_under_way_count_against_the_demand():
    assert pump(1000, idle=3, in_flight=1000) == [[], [], [], []]  # wait for the weights
    assert pump(1000, idle=3, in_flight=400) == [[200], [200], [200], []]


def test_collect_ahead_keeps_idle_workers_collecting_past_the_demand():
    assert pump(1000, ahead=1200, idle=3, in_flight=1000) == [[400], [400], [400], []]
    assert pump(1000, ahead=1000) == [[500]] * 4


def test_workers_holding_more_than_a_buffer_in_rows_collect_through_the_update():
    """4 workers that each held up to 700 steps in rows: 2,800 against a buffer of 1,000.
    A row then spans updates whatever they do: they go on past the demand by the 1,800
    their rows hold beyond the buffer, instead of waiting for its weights."""
    assert pump(1000, idle=3, in_flight=1000, rows=700) == [[600], [600], [600], []]
    assert pump(400, buffer=1000, idle=3, in_flight=400, rows=700) == [[600], [600], [600], []]


def test_rows_within_a_buffer_change_nothing():
    assert pump(1000, idle=3, in_flight=1000, rows=250) == [[], [], [], []]
    assert pump(1000, idle=3, in_flight=400, rows=250) == [[200], [200], [200], []]


def test_a_workers_rows_are_the_most_it_held_and_a_learners_buffer_its_largest_demand():
    demand = Demand()
    for held in (300, 120, 0):
        demand.rows_seen(0, {"A": Counts(in_progress=held), "B": Counts(in_progress=held // 3)})
    demand.rows_seen(1, {"A": Counts(in_progress=200)})
    for wanted in (None, 2401, 700, 1):
        demand.answered(wanted)
    assert (demand.wanted, demand.buffer) == (1, 2401)
    assert demand.rows_beyond_buffer([0, 1]) == 0  # 400 + 200 in rows
    assert Demand().rows_beyond_buffer([0]) == 0
    demand.buffer = 500
    assert demand.rows_beyond_buffer([0, 1]) == 100
    assert demand.rows_beyond_buffer([1]) == 0  # a worker retired: its rows left with it


@pytest.mark.parametrize("horizon", [16, 64])
def test_no_worker_is_asked_for_less_than_a_row(horizon):
    """Rows arrive whole: a smaller ask would return after the same row, one more trip."""
    assert pump(100, horizon=horizon) == [[max(25, horizon)]] * 4


def test_a_learner_with_all_its_steps_gets_no_collect_not_even_ahead():
    assert pump(0, ahead=1200) == [[], [], [], []]


def test_the_learners_newest_answer_is_its_demand_whatever_order_ray_reports(
    ray_session, monkeypatch
):
    """Answers taken oldest first: a consumer that emptied the learner's queue asked again,
    and that newer answer (a demand again) must not be overwritten by the older one (none:
    full), or every worker would wait for ever."""
    import rollout.serving.service as service_module

    @ray_session.remote(num_cpus=0)
    class Answers:
        def __init__(self) -> None:
            self.calls = 0

        def submit(self, segments: list) -> tuple[int, int]:
            self.calls += 1
            return 0, [0, 300, 0][self.calls - 1]  # full, emptied and asked again, full

    learner = Answers.remote()
    config = ServiceConfig(UnityConfig(None), num_workers=1)
    service = RolloutService(config, actor_factory, learner=learner)
    service._submits = [learner.submit.remote([]) for _ in range(2)]
    ray_session.get(service._submits)
    real = ray_session.wait

    def newest_first(refs: list, **options: object) -> tuple[list, list]:
        ready, rest = real(refs, **options)
        return list(reversed(ready)), rest

    monkeypatch.setattr(service_module.ray, "wait", newest_first)
    service._drain_submits(block=False)
    assert service.demand.wanted == 300 and service._submits == []
    ray_session.kill(learner)
