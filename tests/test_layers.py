"""Layers go one way. Every product package is listed with the packages it may import;
the list itself must be a hierarchy (no import runs back up), every import of every file
(lazy and type-only ones too) must follow it, no module may import itself back through
others, and the driver is the one package that wires the actor side to the learners."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# package -> what else of ours it may import (a package, or one module of it)
ALLOWED: dict[str, set[str]] = {
    "mlagents_compat": set(),  # the leaf that makes mlagents-envs import
    "batches": set(),  # the vocabulary and contracts both sides speak
    "demonstrations": {"batches", "mlagents_compat"},  # ML-Agents .demo files
    "unitysim": {"mlagents_compat"},  # plays Unity: knows nothing of the trainer
    "learners": {"batches"},
    "rollout": {"batches", "mlagents_compat", "unitysim.launcher"},
    "gymnasium_adapters": {"batches", "rollout"},
    "torchrl_adapters": {"batches", "rollout"},  # a torchrl collector over the service
    "driver": {"batches", "demonstrations", "learners", "mlagents_compat", "rollout", "unitysim"},
    "testkit": {"batches", "driver", "learners", "mlagents_compat", "rollout", "unitysim"},
}
NOT_PACKAGES = {"tests", "benchmarks", "scripts", "deploy", "docs", "config"}


def imports_of(path: Path, sources: bool = False) -> set[str]:
    """Everything a file imports by absolute name: ``import X.Y`` as ``X.Y``, ``from X
    import y`` as ``X.y``, and with ``sources`` ``X`` too (``y`` may be a name that ``X``'s
    ``__init__`` gives)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if sources:
                found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def crossing(package: str, root: Path = ROOT) -> list[str]:
    allowed = ALLOWED[package] | {package}
    wrong = []
    for path in sorted((root / package).rglob("*.py")):
        for module in imports_of(path):
            if module.split(".")[0] not in ALLOWED:
                continue
            if any(module == a or module.startswith(a + ".") for a in allowed):
                continue
            wrong.append(f"{path.relative_to(root)} imports {module}")
    return wrong


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Our modules and the modules of ours each imports (a package's ``__init__`` when
    the name is not a module of its own)."""
    paths = {
        module_name(p, root): p
        for package in ALLOWED
        if (root / package).is_dir()
        for p in (root / package).rglob("*.py")
    }
    graph: dict[str, set[str]] = {}
    for name, path in paths.items():
        targets = set()
        for imported in imports_of(path, sources=True):
            while imported and imported not in paths:
                imported = imported.rpartition(".")[0]
            if imported and imported != name:
                targets.add(imported)
        graph[name] = targets
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one node (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for target in graph.get(node, ()):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_every_package_is_in_the_table():
    packages = {
        p.name
        for p in ROOT.iterdir()
        if (p / "__init__.py").is_file() and p.name not in NOT_PACKAGES
    }
    assert packages == set(ALLOWED)


def test_the_table_is_a_hierarchy():
    """No package may import one that may import it back, however indirectly."""
    graph = {p: {a.split(".")[0] for a in allowed} for p, allowed in ALLOWED.items()}
    assert circles(graph) == []


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_imports_go_one_way(package):
    assert crossing(package) == []


def test_no_import_circles():
    assert circles(module_graph()) == []


def test_the_driver_alone_wires_rollout_to_learners():
    for package in ALLOWED:
        if package in {"driver", "testkit"}:
            continue
        assert not {"rollout", "learners"} <= {a.split(".")[0] for a in ALLOWED[package]}


def test_the_product_never_imports_testkit():
    assert [p for p, allowed in ALLOWED.items() if "testkit" in allowed] == []


def test_the_check_sees_a_crossing(tmp_path):
    bad = tmp_path / "learners"
    bad.mkdir()
    (bad / "x.py").write_text(
        "from rollout.serving.service import RolloutService\nimport batches.keys\n"
    )
    assert crossing("learners", tmp_path) == [
        "learners/x.py imports rollout.serving.service.RolloutService"
    ]


def test_the_check_sees_a_circle_through_a_lazy_import(tmp_path):
    package = tmp_path / "learners"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from learners.b import thing\n")
    (package / "b.py").write_text("def f():\n    from learners import c\n")
    (package / "c.py").write_text("import learners.a\n")
    (package / "d.py").write_text("from learners.a import thing\n")
    assert circles(module_graph(tmp_path)) == [["learners.a", "learners.b", "learners.c"]]


def test_the_check_sees_a_module_that_imports_its_package_back(tmp_path):
    """``from package import sibling`` runs the package's ``__init__``: a circle where that
    ``__init__`` imports the module doing it."""
    package = tmp_path / "learners"
    package.mkdir()
    (package / "__init__.py").write_text("from learners.a import thing\n")
    (package / "a.py").write_text("from learners import b\nthing = 1\n")
    (package / "b.py").write_text("")
    assert circles(module_graph(tmp_path)) == [["learners", "learners.a"]]


def test_no_module_sprawls():
    """A ceiling that catches sprawl, not a number to squeeze a cohesive module under: the
    product, its tooling, tests and benchmarks."""
    folders = [*ALLOWED, "tests", "benchmarks"]
    long = {
        str(path.relative_to(ROOT)): lines
        for folder in folders
        for path in (ROOT / folder).rglob("*.py")
        if (lines := len(path.read_text().splitlines())) > 600
    }
    assert long == {}


# the folders whose contents have several roles, and the sub-packages that give them one each
BY_ROLE = {
    "learners": {"acting", "algorithms", "host", "networks", "reward_signals", "trainer_config"},
    "driver": {"recording", "training", "tuning"},
    "rollout": {"collecting", "environment", "serving"},
}


@pytest.mark.parametrize("package", sorted(BY_ROLE))
def test_a_folder_of_many_roles_holds_its_roles_in_sub_packages(package):
    """At most 12 modules side by side, the rest in sub-packages named for what they do."""
    folder = ROOT / package
    modules = [p.name for p in folder.glob("*.py") if p.name != "__init__.py"]
    subs = {p.parent.name for p in folder.glob("*/__init__.py")}
    assert len(modules) <= 12, modules
    assert subs == BY_ROLE[package]
    for sub in subs:
        assert ast.get_docstring(ast.parse((folder / sub / "__init__.py").read_text()))
