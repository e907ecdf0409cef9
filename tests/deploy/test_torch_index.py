"""scripts/check-torch-index.py, which stops an image build at once when torch's CPU wheel
cannot be had (instead of pip silently taking the CUDA build), against an index served
here on loopback."""

from __future__ import annotations

import functools
import http.server
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts/check-torch-index.py"


@pytest.fixture
def index(tmp_path):
    """An index like torch's: INDEX/torch/ lists the wheels."""
    (tmp_path / "cpu" / "torch").mkdir(parents=True)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield tmp_path / "cpu" / "torch", f"http://127.0.0.1:{server.server_address[1]}/cpu"
    finally:
        server.shutdown()
        server.server_close()


def check(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=60
    )


def test_an_index_with_the_cpu_wheel_passes(index):
    wheels, url = index
    tag = f"cp{sys.version_info[0]}{sys.version_info[1]}"
    (wheels / f"torch-2.13.0+cpu-{tag}-{tag}-manylinux_2_28_x86_64.whl").write_bytes(b"")
    assert check(url).returncode == 0


def test_an_index_without_it_stops_with_one_line(index):
    wheels, url = index
    (wheels / "torch-2.13.0-cp311-cp311-manylinux_2_28_x86_64.whl").write_bytes(b"")  # CUDA
    result = check(url)
    assert result.returncode == 1
    assert result.stdout.count("\n") == 1 and "has no torch-2.13.0+cpu wheel" in result.stdout


def test_an_unreachable_index_stops_with_one_line():
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    result = check(f"http://127.0.0.1:{port}/cpu")
    assert result.returncode == 1
    assert "is unreachable" in result.stdout and "PIP_EXTRA_INDEX_URL" in result.stdout


def test_the_installed_torch_here_is_the_cpu_build():
    assert check("--installed").returncode == 0
