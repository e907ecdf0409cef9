"""Each fault flag of unitysim makes the real UnityEnvironment raise what it raises for the
real failure, in bounded time, and leaves no process behind."""

from __future__ import annotations

import time

import numpy as np
import pytest
from mlagents_envs.exception import (
    UnityCommunicatorStoppedException,
    UnityEnvironmentException,
    UnityTimeOutException,
)

pytestmark = pytest.mark.integration
BALL = "3DBall?team=0"


def run_steps(env, steps: int) -> None:
    env.reset()
    for _ in range(steps):
        env.step()


@pytest.mark.parametrize(
    ("flags", "error", "message"),
    [
        (["--sim-crash-after", "3"], UnityEnvironmentException, "return code 3"),
        (["--sim-status-after", "2"], UnityCommunicatorStoppedException, "Communicator"),
        (["--sim-oversize-after", "2"], UnityEnvironmentException, "return code 1"),
        (["--sim-nan-after", "2"], RuntimeError, "NaN"),
    ],
    ids=["crash", "status-500", "oversized-message", "nan-observations"],
)
def test_fault_raises_the_real_exception(open_env, flags, error, message):
    with (
        open_env("3DBall", additional_args=flags) as env,
        pytest.raises(error, match=message),
    ):
        run_steps(env, 10)


def test_hang_times_out(open_env):
    """The test is about the hang's timeout: 10 s, not mlagents' 60 (a hang costs two of
    them, the step's and close()'s wait before the kill). The start keeps mlagents' 60 s:
    beside two busy processes a player took more than 10 s to connect. mlagents-envs reads
    the wait from these two attributes on every exchange and at close."""
    with open_env("3DBall", additional_args=["--sim-hang-after", "2"]) as env:
        env._communicator.timeout_wait = env._timeout_wait = 10
        with pytest.raises(UnityTimeOutException):
            run_steps(env, 10)


def test_slow_answers_are_slow_but_correct(open_env):
    with open_env("3DBall", additional_args=["--sim-delay-ms", "150"]) as env:
        env.reset()
        started = time.monotonic()
        for _ in range(3):
            env.step()
        assert time.monotonic() - started >= 0.45
        assert len(env.get_steps(BALL)[0]) == 12


def test_incompatible_communication_version_is_refused(open_env):
    with (
        pytest.raises(UnityEnvironmentException, match="not compatible"),
        open_env("3DBall", additional_args=["--sim-communication-version", "2.0.0"]),
    ):
        pass


def test_faults_also_come_from_environment_variables(open_env, monkeypatch):
    monkeypatch.setenv("UNITYSIM_CRASH_AFTER", "2")
    with open_env("Basic") as env, pytest.raises(UnityEnvironmentException, match="return code 3"):
        run_steps(env, 5)


def test_nan_fault_only_from_its_step(open_env):
    with open_env("3DBall", additional_args=["--sim-nan-after", "4"]) as env:
        run_steps(env, 3)
        assert np.isfinite(env.get_steps(BALL)[0].obs[0]).all()
        with pytest.raises(RuntimeError, match="NaN"):
            env.step()
