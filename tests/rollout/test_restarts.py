"""Restart limits: by rate and lifetime (ML-Agents' keys), and launches that fail before
a step. Unit tests on a fake clock, then real players that crash or hang on every launch."""

from __future__ import annotations

import logging
import re

import pytest

from learners.acting.factory import actor_factory
from rollout.collecting.collector import Collector
from rollout.environment.ports import PortAllocator, PortRange
from rollout.environment.restarts import RestartBudget, RestartPolicy, RestartRefused
from rollout.environment.unity import UnityConfig, UnityError, UnityInstance, UnityStartError
from tests.helpers import wait_gone


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def productive_restarts(budget: RestartBudget, clock: Clock, count: int, every_s: float) -> None:
    for _ in range(count):
        budget.healthy()
        clock.now += every_s
        budget.admit("build", "crash")


def test_a_crash_prone_but_productive_build_restarts_without_end():
    clock = Clock()
    budget = RestartBudget(RestartPolicy(), clock)  # defaults: 20 per 60 s, no lifetime limit
    productive_restarts(budget, clock, 1000, every_s=3.0 + 1e-6)
    assert budget.restarts == 1000


def test_the_rate_limit_counts_restarts_within_the_period():
    clock = Clock()
    budget = RestartBudget(RestartPolicy(rate_limit_n=3, rate_limit_period_s=10.0), clock)
    productive_restarts(budget, clock, 3, every_s=1.0)
    with pytest.raises(RestartRefused, match=r"more than 3 restarts within 10 s .*last failure: x"):
        budget.healthy()
        budget.admit("build", "x")
    clock.now += 8.0  # the first restart (at 1 s) has left the window
    budget.admit("build", "y")
    assert budget.restarts == 4


def test_the_lifetime_limit_is_ml_agents_max_lifetime_restarts():
    clock = Clock()
    budget = RestartBudget(RestartPolicy(max_lifetime_restarts=2), clock)
    productive_restarts(budget, clock, 2, every_s=3600.0)
    with pytest.raises(RestartRefused, match="lifetime limit of 2 restarts reached"):
        productive_restarts(budget, clock, 1, every_s=3600.0)


def test_launches_that_fail_before_a_step_stop_quickly_with_backoff():
    budget = RestartBudget(RestartPolicy(max_failed_starts=3, backoff_s=0.5), Clock())
    delays = [budget.admit("build", "crash") for _ in range(3)]
    assert delays == [0.5, 1.0, 2.0]
    with pytest.raises(RestartRefused, match="4 launches in a row failed before a step"):
        budget.admit("build", "no connection")
    budget.healthy()  # a good step: the backoff starts over
    assert budget.admit("build", "crash") == 0.5


PORTS = PortRange(24500, 24599)
LAUNCHED = re.compile(r"^Unity .* on port \d+ \(pid (\d+)\)$")  # UnityInstance.start's line


@pytest.fixture
def allocator(tmp_path):
    allocator = PortAllocator(PORTS, tmp_path / "ports")
    yield allocator
    assert allocator.leases() == {}, "a test left a port leased"


def faulty_3dball(
    allocator: PortAllocator, flags: tuple[str, ...], policy: RestartPolicy, timeout_wait: int = 60
) -> Collector:
    """A collector of unitysim 3DBall whose every player has the fault ``flags``."""
    config = UnityConfig(
        "unitysim:3DBall", additional_args=flags, timeout_wait=timeout_wait, restarts=policy
    )
    return Collector(config, actor_factory, horizon=16, allocator=allocator)


def shorten_answer_wait(monkeypatch: pytest.MonkeyPatch, seconds: int) -> None:
    """Once a player has connected (within ``timeout_wait``), it must answer each exchange
    within ``seconds``: mlagents-envs reads the wait from these two attributes each time."""
    start = UnityInstance.start

    def start_then_shorten(self: UnityInstance) -> None:
        start(self)
        self.env._communicator.timeout_wait = self.env._timeout_wait = seconds

    monkeypatch.setattr(UnityInstance, "start", start_then_shorten)


@pytest.mark.integration
@pytest.mark.parametrize(
    ("flags", "answer_wait"),
    [(("--sim-crash-after", "300"), None), (("--sim-hang-after", "100"), 6)],
    ids=["crash", "hang"],
)
def test_a_fault_on_every_launch_costs_restarts_not_the_run(
    allocator, flags, answer_wait, caplog, monkeypatch
):
    """Each launch gives good steps, then crashes (or hangs: found within 6 s and killed at
    once; each player still gets mlagents' 60 s to connect, as a loaded machine needs);
    after six restarts collection goes on, and no player is left. A launch that does not
    connect in time is one more restart, not the run's end: the players are counted as the
    launches announce them."""
    if answer_wait is not None:
        shorten_answer_wait(monkeypatch, answer_wait)
    caplog.set_level(logging.INFO, logger="rollout.environment.unity")
    collector = faulty_3dball(allocator, flags, RestartPolicy(backoff_s=0.0))
    served: set[int] = set()
    try:
        while collector.snapshot().restarts < 6:
            collector.collect(min_steps=200)
            served.add(collector.unity.player_pid)
        assert sum(len(s) for s in collector.collect(min_steps=200)) >= 200
    finally:
        collector.close()
    launched = {int(m[1]) for r in caplog.records if (m := LAUNCHED.search(r.getMessage()))}
    reasons = [r.getMessage() for r in caplog.records if r.getMessage().startswith("restarting")]
    assert len(reasons) >= 6
    fault = "return code" if "crash" in flags[0] else "did not answer within timeout_wait"
    assert all(fault in reason or "did not connect" in reason for reason in reasons), reasons
    assert served <= launched and len(served) >= 2  # new players served steps after faults
    assert all(wait_gone(pid) for pid in launched)
    assert collector.snapshot().dropped_steps > 0  # partial rows of each failed player


@pytest.mark.integration
def test_a_build_that_fails_at_every_launch_stops_with_its_cause(allocator):
    policy = RestartPolicy(max_failed_starts=3, backoff_s=0.01)
    collector = faulty_3dball(allocator, ("--sim-crash-after", "1"), policy)
    try:
        with pytest.raises(UnityError, match="4 launches in a row failed before a step"):
            collector.collect(min_steps=10)
        assert collector.snapshot().restarts == 3
    finally:
        collector.close()  # no player left: the suite's autouse fixture checks it


@pytest.mark.integration
def test_restarts_whose_players_never_come_up_are_counted(allocator, monkeypatch):
    """The player crashes; every relaunch then fails to connect (as a start slower than
    ``timeout_wait`` does): the metrics count each of those restarts, not only the ones
    that came up."""
    policy = RestartPolicy(max_lifetime_restarts=2, backoff_s=0.0)
    collector = faulty_3dball(allocator, ("--sim-crash-after", "40"), policy)
    try:
        collector.collect(min_steps=1)  # the first player is up

        def never_connects() -> None:
            raise UnityStartError("the player did not connect within timeout_wait")

        monkeypatch.setattr(collector.unity, "start", never_connects)
        with pytest.raises(UnityError, match="lifetime limit of 2 restarts reached"):
            for _ in range(20):
                collector.collect(min_steps=10)
        assert collector.snapshot().restarts == 2
    finally:
        collector.close()
