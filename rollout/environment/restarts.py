"""When a failed Unity instance may start again.

A real build that crashes once an hour must train for days, so restarts are limited by
rate, as mlagents-learn limits them (``--restarts-rate-limit-n`` restarts within
``--restarts-rate-limit-period-s``), and by a lifetime count (``--max-lifetime-restarts``)
that is off by default. The keys mean what they mean in ML-Agents; the defaults are ours
(ML-Agents: 1 per 60 s, 10 in a lifetime): a build that gives hundreds of good steps
between crashes keeps training. A build that fails before its first step, launch after
launch, stops after ``max_failed_starts`` such launches with the last failure as its cause.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass


class RestartRefused(RuntimeError):
    """No more restarts: the message names the limit and the last failure."""


@dataclass(frozen=True)
class RestartPolicy:
    max_lifetime_restarts: int = -1  # -1: no limit
    rate_limit_n: int = 20  # restarts allowed within rate_limit_period_s; -1: no limit
    rate_limit_period_s: float = 60.0
    max_failed_starts: int = 5  # launches in a row that failed before a good step
    backoff_s: float = 0.5  # before a restart; doubled per failed start, capped
    max_backoff_s: float = 30.0

    def __post_init__(self) -> None:
        if self.rate_limit_period_s <= 0:
            raise ValueError(f"rate_limit_period_s: positive, got {self.rate_limit_period_s:g}")
        if self.max_failed_starts < 0:
            raise ValueError(f"max_failed_starts: 0 or more, got {self.max_failed_starts}")


class RestartBudget:
    """Counts one instance's restarts against a :class:`RestartPolicy`."""

    def __init__(self, policy: RestartPolicy, clock: Callable[[], float] = time.monotonic) -> None:
        self.policy = policy
        self.clock = clock
        self.restarts = 0
        self.failed_starts = 0  # failures since the last good step
        self._recent: deque[float] = deque()

    def healthy(self) -> None:
        """A good step: the instance that failed last was productive."""
        self.failed_starts = 0

    def admit(self, build: str, reason: str) -> float:
        """Count a restart, or raise :class:`RestartRefused`; the seconds to wait first."""
        policy, now = self.policy, self.clock()
        self.failed_starts += 1
        if self.failed_starts > policy.max_failed_starts:
            raise RestartRefused(
                f"{build}: {self.failed_starts} launches in a row failed before a step "
                f"(last failure: {reason})"
            )
        if 0 <= policy.max_lifetime_restarts <= self.restarts:
            raise RestartRefused(
                f"{build}: lifetime limit of {policy.max_lifetime_restarts} restarts reached "
                f"(--max-lifetime-restarts; last failure: {reason})"
            )
        while self._recent and self._recent[0] <= now - policy.rate_limit_period_s:
            self._recent.popleft()
        if 0 <= policy.rate_limit_n <= len(self._recent):
            raise RestartRefused(
                f"{build}: more than {policy.rate_limit_n} restarts within "
                f"{policy.rate_limit_period_s:g} s (--restarts-rate-limit-n, "
                f"--restarts-rate-limit-period-s; last failure: {reason})"
            )
        self._recent.append(now)
        self.restarts += 1
        return min(policy.backoff_s * 2 ** (self.failed_starts - 1), policy.max_backoff_s)
