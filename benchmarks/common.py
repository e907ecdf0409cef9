"""What every benchmark shares: the repository's paths, where it ran (``machine``), and the
result file it saves in ``benchmarks/results/`` (``record``, ``save_result``), the file
``benchmarks/plots.py`` draws from.

A result file is one JSON object per benchmark question: ``question``, ``benchmark`` (the
module), ``machine``, ``date``, ``commit`` (None where unknown), ``command``, then the
benchmark's own figures. A file transcribed from the docs has a ``source`` too.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
# ML-Agents' own example configs: the release's whole tree, ``<trainer>/<Name>.yaml``, the
# files the suite runs unchanged (tests/mlagents_configs/README.md); and the variants made
# here, each one of them less one section, to show what that feature does
MLAGENTS_CONFIGS = ROOT / "tests" / "mlagents_configs"
CONFIG_VARIANTS = ROOT / "benchmarks" / "config_variants"


def mlagents_config(name: str) -> Path:
    """ML-Agents' config ``name`` (``ppo/Pyramids.yaml``), or a variant made here
    (``ppo/Pyramids_nocuriosity.yaml``)."""
    for tree in (MLAGENTS_CONFIGS, CONFIG_VARIANTS):
        if (tree / name).is_file():
            return tree / name
    raise SystemExit(
        f"no config {name!r} in {MLAGENTS_CONFIGS.relative_to(ROOT)}/ or "
        f"{CONFIG_VARIANTS.relative_to(ROOT)}/: name one as <trainer>/<Name>.yaml"
    )


def machine() -> dict[str, Any]:
    """Cores, CPU model, Python, date; the GPU where torch is imported and sees one."""
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    found: dict[str, Any] = {
        "nproc": os.cpu_count(),
        "affinity": len(os.sched_getaffinity(0)),
        "cpu": model,
        "python": platform.python_version(),
        "date": now(),
    }
    torch = sys.modules.get("torch")  # not imported here: most benchmarks do not need it
    if torch is not None and torch.cuda.is_available():
        found["gpu"] = torch.cuda.get_device_name()
    return found


def now() -> str:
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")


def commit() -> str | None:
    """The checkout's commit, with ``+changes`` where tracked files differ from it."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"],
            cwd=ROOT, capture_output=True, text=True, check=True,
        ).stdout.strip()  # fmt: skip
        changed = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=ROOT, capture_output=True, text=True, check=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+changes" if changed else "")


def command() -> str:
    """This benchmark's command line, as run from the repository root."""
    spec = getattr(sys.modules["__main__"], "__spec__", None)
    program = ["-m", spec.name] if spec is not None else [sys.argv[0]]
    return shlex.join([".venv/bin/python", *program, *sys.argv[1:]])


def record(question: str, **figures: Any) -> dict[str, Any]:
    """A result file's contents: ``question``, where, when, which commit and command, then
    ``figures`` (the benchmark's own keys)."""
    spec = getattr(sys.modules["__main__"], "__spec__", None)
    return {
        "question": question,
        "benchmark": spec.name if spec is not None else sys.argv[0],
        "machine": machine(),
        "date": now(),
        "commit": commit(),
        "command": command(),
        **figures,
    }


def save_result(path: Path | str, contents: dict[str, Any]) -> Path:
    """Write ``contents`` (``record``'s) to ``path``, its folder made if need be."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(contents, indent=2, default=str) + "\n")
    return path
