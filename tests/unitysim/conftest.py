"""Fixtures for driving unitysim through the real ``UnityEnvironment`` over real gRPC."""

from __future__ import annotations

import contextlib
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from mlagents_envs.environment import UnityEnvironment

from tests.helpers import free_port
from unitysim.launcher import build


@pytest.fixture(scope="session")
def builds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory with a launcher for every unitysim environment."""
    directory = tmp_path_factory.mktemp("builds")
    build(directory)
    return directory


OpenEnv = Callable[..., contextlib.AbstractContextManager[UnityEnvironment]]


@pytest.fixture
def open_env(builds: Path, tmp_path: Path) -> OpenEnv:
    """``with open_env("3DBall", seed=1) as env:`` launches the stand-in like a build and
    always closes it; the player process must be gone afterwards."""

    @contextlib.contextmanager
    def opener(name: str, **kwargs: object) -> Iterator[UnityEnvironment]:
        kwargs.setdefault("no_graphics", False)  # as a real build, by default
        kwargs.setdefault("log_folder", str(tmp_path))
        env = UnityEnvironment(file_name=str(builds / name), base_port=free_port(), **kwargs)
        process = env._process
        try:
            yield env
        finally:
            with contextlib.suppress(Exception):
                env.close()
            if process is not None:
                try:
                    process.wait(timeout=5)  # also reaps a player mlagents killed
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait(5)
                    pytest.fail(f"{name}: player still running 5 s after close()")

    return opener
