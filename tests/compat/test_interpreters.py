"""The compat suite also passes under Python 3.12 and 3.13 (no distutils), and under the
original pins of mlagents-envs (Python 3.10, protobuf 3.20), where compat is a no-op.

Each interpreter gets a small cached virtual environment in ``.venv-compat/``.
"""

import glob
import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CHILD_FLAG = "UNITY_ROLLOUT_COMPAT_CHILD"
MODERN = ["grpcio", "protobuf", "numpy", "Pillow", "pytest", "pytest-timeout"]
ORIGINAL_PINS = [
    "grpcio==1.48.2",
    "protobuf==3.20.3",
    "numpy==1.23.5",
    "Pillow",
    "pytest",
    "pytest-timeout",
]

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(CHILD_FLAG in os.environ, reason="already inside an interpreter check"),
]


def find_python(version: str) -> str | None:
    candidates = [shutil.which(f"python{version}")]
    pyenv_root = os.environ.get("PYENV_ROOT", os.path.expanduser("~/.pyenv"))
    candidates += sorted(glob.glob(f"{pyenv_root}/versions/{version}.*/bin/python{version}"))
    for candidate in filter(None, candidates):
        probe = subprocess.run([candidate, "--version"], capture_output=True, text=True)
        if probe.returncode == 0 and probe.stdout.startswith(f"Python {version}."):
            return candidate
    return None


def compat_venv(name: str, python: str, packages: list[str], constrained: bool) -> Path:
    """Create (or reuse, when its inputs are unchanged) a venv with mlagents-envs in it."""
    venv = ROOT / ".venv-compat" / name
    constraints = ["-c", str(ROOT / "constraints.txt")] if constrained else []
    stamp = hashlib.sha256(repr((python, packages, constraints)).encode()).hexdigest()
    if constrained:
        stamp += hashlib.sha256((ROOT / "constraints.txt").read_bytes()).hexdigest()
    stamp_file = venv / ".installed"
    if stamp_file.exists() and stamp_file.read_text() == stamp:
        return venv
    subprocess.run([python, "-m", "venv", "--clear", str(venv)], check=True)
    pip = [str(venv / "bin" / "python"), "-m", "pip", "-q", "--disable-pip-version-check"]
    subprocess.run([*pip, "install", *constraints, *packages], check=True)
    subprocess.run(
        [*pip, "install", "--no-deps", "--ignore-requires-python", "mlagents-envs==1.1.0"],
        check=True,
    )
    stamp_file.write_text(stamp)
    return venv


def run_compat_suite(venv: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, CHILD_FLAG: "1", "PYTHONPATH": str(ROOT)}
    env.pop("PYTEST_ADDOPTS", None)
    return subprocess.run(
        [
            str(venv / "bin" / "python"),
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            str(ROOT / "tests" / "compat"),
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.mark.parametrize("version", ["3.12", "3.13"])
def test_compat_suite_on_newer_python(version):
    python = find_python(version)
    if python is None:
        pytest.skip(f"no python{version} interpreter on this machine")
    venv = compat_venv(f"py{version}", python, MODERN, constrained=True)
    result = run_compat_suite(venv)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert " passed" in result.stdout and " failed" not in result.stdout


def test_compat_is_a_no_op_under_the_original_pins():
    python = find_python("3.10")
    if python is None:
        pytest.skip("no python3.10 interpreter on this machine")
    venv = compat_venv("py3.10-original-pins", python, ORIGINAL_PINS, constrained=False)
    probe = subprocess.run(
        [
            str(venv / "bin" / "python"),
            "-c",
            "import mlagents_compat as c; print(c.install()); import mlagents_envs.environment",
        ],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        check=True,
    )
    assert probe.stdout.strip() == "()"
    result = run_compat_suite(venv)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


def test_this_interpreter_is_the_pinned_one():
    assert sys.version_info[:2] >= (3, 11)
