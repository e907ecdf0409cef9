"""The port registry of the real-Ray worker and service tests, checked empty after each."""

from __future__ import annotations

import pytest

from rollout.environment.ports import PortAllocator
from tests.rollout.workers import PORTS


@pytest.fixture
def registry(tmp_path):
    directory = tmp_path / "ports"
    yield str(directory)
    assert PortAllocator(PORTS, directory).leases() == {}, "a test left a port leased"
