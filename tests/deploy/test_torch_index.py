"""scripts/check-torch-index.py, which chooses torch's index for the image's TORCH build
(cpu, a CUDA build, any) and stops an image build at once when that build's wheel cannot be
had (instead of pip silently taking another build), against an index served here on
loopback."""

from __future__ import annotations

import functools
import http.server
import importlib.util
import re
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts/check-torch-index.py"
TAG = f"cp{sys.version_info[0]}{sys.version_info[1]}"


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


def module():
    spec = importlib.util.spec_from_file_location("check_torch_index", SCRIPT)
    loaded = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(loaded)
    return loaded


def one_line_error(result: subprocess.CompletedProcess, status: int = 1) -> str:
    assert result.returncode == status, result
    assert result.stdout == "" and result.stderr.count("\n") == 1, result
    assert result.stderr.startswith("error: ")
    return result.stderr


def test_an_index_with_the_cpu_wheel_passes(index):
    wheels, url = index
    (wheels / f"torch-2.13.0+cpu-{TAG}-{TAG}-manylinux_2_28_x86_64.whl").write_bytes(b"")
    assert check(url).returncode == 0
    assert check("--torch", "cpu", url).returncode == 0


def test_an_index_without_it_stops_with_one_line(index):
    wheels, url = index
    (wheels / "torch-2.13.0-cp311-cp311-manylinux_2_28_x86_64.whl").write_bytes(b"")  # CUDA
    assert "has no torch-2.13.0+cpu wheel" in one_line_error(check(url))


def test_an_unreachable_index_stops_with_one_line():
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    error = one_line_error(check(f"http://127.0.0.1:{port}/cpu"))
    # the line scripts/image-check.sh expects of a build with an unreachable index
    assert re.search(
        r"error: torch's CPU build is asked for \(TORCH=cpu\) but .* is unreachable", error
    )
    assert "PIP_EXTRA_INDEX_URL" in error and "TORCH=any" in error


def test_the_installed_torch_here_is_the_cpu_build():
    assert check("--installed").returncode == 0
    assert check("--torch", "cpu", "--installed").returncode == 0


def test_a_cuda_build_is_checked_for_its_own_wheel(index):
    wheels, url = index
    (wheels / f"torch-2.13.0%2Bcu130-{TAG}-{TAG}-manylinux_2_28_x86_64.whl").write_bytes(b"")
    assert check("--torch", "cu130", url).returncode == 0
    error = one_line_error(check("--torch", "cu126", url))
    assert "torch's CUDA 12.6 build is asked for (TORCH=cu126)" in error
    assert "has no torch-2.13.0+cu126 wheel" in error
    assert "has no torch-2.13.0+cpu wheel" in one_line_error(check(url))  # the CPU default


def test_a_cuda_build_with_the_cpu_torch_installed_stops_with_one_line():
    error = one_line_error(check("--torch", "cu130", "--installed"))
    assert "(CPU) was installed" in error and "TORCH=cu130" in error


def test_any_checks_nothing():
    assert check("--torch", "any", "http://127.0.0.1:9/cpu").returncode == 0
    assert check("--torch", "any", "--installed").returncode == 0


@pytest.mark.parametrize(
    "build, index",
    [
        ("cpu", "https://download.pytorch.org/whl/cpu"),
        ("cu126", "https://download.pytorch.org/whl/cu126"),
        ("cu130", "https://download.pytorch.org/whl/cu130"),
        ("cu132", "https://download.pytorch.org/whl/cu132"),
        ("any", "https://download.pytorch.org/whl/cpu"),
    ],
)
def test_index_for_a_build(build, index):
    result = check("--index-for", build)
    assert result.returncode == 0 and result.stdout == index + "\n"
    assert check("--index-for", build, "").stdout == index + "\n"  # ARG PIP_EXTRA_INDEX_URL=
    mirror = check("--index-for", build, "http://127.0.0.1:8000/whl/x")
    assert mirror.stdout == "http://127.0.0.1:8000/whl/x\n"


@pytest.mark.parametrize("args", [("--index-for", "cu121"), ("--torch", "rocm", "--installed")])
def test_a_build_that_is_not_one_stops_with_one_line_naming_them(args):
    error = one_line_error(check(*args), status=2)
    assert f"TORCH={args[1]}:" in error
    assert "cpu (the default), cu126, cu130 or cu132 (CUDA), or any" in error


def test_the_builds_are_those_of_the_pinned_torch():
    """A new torch pin must revisit BUILDS: torch changes its CUDA builds between releases
    (2.12 dropped 12.8; 2.15 drops 12.6)."""
    checker = module()
    pin = checker.pinned_torch()
    assert re.match(rf"{re.escape(checker.TORCH_SERIES)}\.\d+$", pin), (
        f"torch=={pin} is pinned but BUILDS lists torch {checker.TORCH_SERIES}'s builds: "
        "update TORCH_SERIES and BUILDS from torch's release matrix"
    )
    assert checker.BUILDS["cpu"] == "CPU"
    assert all(re.fullmatch(r"cu\d{3}", build) for build in checker.BUILDS if build != "cpu")
    dockerfile = (ROOT / "Dockerfile").read_text()
    for build in checker.BUILDS:  # the Dockerfile's header names every build
        assert re.search(rf"^#.*\b{build}\b", dockerfile, re.M), build
