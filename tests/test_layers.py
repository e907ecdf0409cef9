"""Layers go one way: ``batches`` (the vocabulary) imports none of the others, ``learners``
never imports ``rollout`` (and so never needs Ray to be tested), ``unitysim`` imports
nothing of ours but the compat loader."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
OURS = {"batches", "learners", "rollout", "unitysim"}
ALLOWED = {  # package -> our packages it may import (module paths allowed one by one)
    "batches": {"batches"},
    "learners": {"batches", "learners"},
    "unitysim": {"unitysim", "rollout.compat"},
}


def imports_of(path: Path) -> set[str]:
    """Everything a file imports by absolute name: ``import X.Y`` as ``X.Y``, ``from X
    import y`` as ``X.y``."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def crossing(package: str) -> list[str]:
    allowed = ALLOWED[package]
    wrong = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for module in imports_of(path):
            if module.split(".")[0] not in OURS:
                continue
            if any(module == a or module.startswith(a + ".") for a in allowed):
                continue
            wrong.append(f"{path.relative_to(ROOT)} imports {module}")
    return wrong


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_imports_go_one_way(package):
    assert crossing(package) == []


def test_the_check_sees_a_crossing(tmp_path, monkeypatch):
    bad = tmp_path / "learners"
    bad.mkdir()
    (bad / "x.py").write_text("from rollout.service import RolloutService\nimport batches.keys\n")
    monkeypatch.setattr(f"{__name__}.ROOT", tmp_path)
    assert crossing("learners") == ["learners/x.py imports rollout.service.RolloutService"]
