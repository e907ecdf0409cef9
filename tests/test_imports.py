"""Our packages import cleanly and never touch mlagents_envs.envs or its registry.

``mlagents_envs.envs`` iterates ``default_registry``, which downloads a manifest and
needs gym and PettingZoo 1.15 (not installable on 3.11), so importing it would break us.
Our own PettingZoo adapter uses the current PettingZoo.
"""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = (
    "batches",
    "demonstrations",
    "driver",
    "gymnasium_adapters",
    "learners",
    "mlagents_compat",
    "rollout",
    "torchrl_adapters",
    "unitysim",
)

SCRIPT = """
import importlib, json, pkgutil, sys
import mlagents_compat, mlagents_envs.environment  # the README's check
names = []
for package in {packages!r}:
    module = importlib.import_module(package)
    names.append(package)
    for info in pkgutil.walk_packages(module.__path__, package + "."):
        if info.name.endswith("__main__"):
            continue
        importlib.import_module(info.name)
        names.append(info.name)
print(json.dumps({{"imported": names, "modules": sorted(sys.modules)}}))
"""


def test_no_module_imports_mlagents_envs_registry_or_envs():
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(packages=PACKAGES)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert "mlagents_compat" in report["imported"]
    assert "mlagents_envs.environment" in report["modules"]
    forbidden = [
        name
        for name in report["modules"]
        if name.startswith(("mlagents_envs.envs", "mlagents_envs.registry", "gym."))
        or name == "gym"
    ]
    assert forbidden == []


def test_unitysim_does_not_import_rollout_or_learners():
    """Only the tiny compat loader (``mlagents_compat``) is allowed."""
    forbidden = re.compile(
        r"^\s*(from|import)\s+(learners|rollout)\b(?!\.compat\b| import compat\b)"
    )
    offenders = [
        f"{path.relative_to(ROOT)}: {line.strip()}"
        for path in (ROOT / "unitysim").rglob("*.py")
        for line in path.read_text().splitlines()
        if forbidden.match(line)
    ]
    assert offenders == []


def test_cli_help_lists_commands():
    result = subprocess.run(
        [sys.executable, "-m", "driver.cli", "--help"], cwd=ROOT, capture_output=True, text=True
    )
    assert result.returncode == 0
    assert "doctor" in result.stdout


WORKER = (  # its actor class's module, the policy factory it unpickles, one vector behavior
    "import pickle\n"
    "import numpy as np\n"
    "import rollout.collecting.worker\n"
    "from mlagents_envs.base_env import ActionSpec, BehaviorSpec, ObservationSpec\n"
    "from mlagents_envs.base_env import DimensionProperty, ObservationType\n"
    "from learners.acting.factory import actor_factory\n"
    "factory = pickle.loads(pickle.dumps(actor_factory))\n"
    "obs = ObservationSpec((8,), (DimensionProperty.NONE,), ObservationType.DEFAULT, 'v')\n"
    "actor = factory('3DBall?team=0', BehaviorSpec([obs], ActionSpec(2, (3,))))\n"
    "actor.act({'v': np.zeros((4, 8), np.float32)})\n"
)
CAMERA_WORKER = WORKER + (  # and a camera behavior (AnimalArena's shape), acting in numpy
    "pixels = (DimensionProperty.NONE, *(DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,) * 2)\n"
    "camera = ObservationSpec((3, 84, 84), pixels, ObservationType.DEFAULT, 'camera')\n"
    "actor = factory('Arena?team=0', BehaviorSpec([camera, obs], ActionSpec(0, (3, 3))))\n"
    "actor.act({'camera': np.zeros((4, 3, 84, 84), np.uint8), 'v': np.zeros((4, 8), np.float32)})\n"
)
DRIVER = "import driver.cli, driver.training.train\n"  # `unity-rollout train`, before the learner


@pytest.mark.parametrize(
    ("process", "script", "expected", "absent"),
    [
        ("worker", WORKER, ("rollout.collecting.collector", "learners.acting.factory"), ("torch",)),
        ("camera worker", CAMERA_WORKER, ("learners.acting.numpy_images",), ("torch",)),
        ("driver", DRIVER, ("rollout.serving.service", "learners.host.remote"), ("torch",)),
    ],
)
def test_workers_and_the_driver_load_neither_torch_nor_tensordict_nor_torchrl(
    process, script, expected, absent
):
    """tensordict and torchrl (with torch._dynamo) took most of a worker's start, and a
    second of the driver's CPU while Ray starts; segments travel as numpy and become
    TensorDicts in the learner's process only. A worker acting on vector observations
    loads no torch either (1.3 s of CPU and about 180 MB), nor one acting on a camera (it
    was 730-816 MB resident with torch), nor does the driver before its first checkpoint
    (the learner's process does)."""
    script = f"import json, sys\n{script}print(json.dumps(sorted(sys.modules)))\n"
    result = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-3000:]
    modules = json.loads(result.stdout.strip().splitlines()[-1])
    assert all(name in modules for name in expected), process
    forbidden = ("tensordict", "torchrl", *absent)
    assert [m for m in modules if m.split(".")[0] in forbidden] == []
