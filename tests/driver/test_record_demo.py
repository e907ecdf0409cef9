"""``unity-rollout record-demo`` end to end: real unitysim players through the protocol, the
file read back with ``demonstrations.read_demo``, no process, port lease or partial file
left behind, and every mistake one line."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from mlagents_envs.base_env import (
    ActionSpec,
    BehaviorSpec,
    DimensionProperty,
    ObservationSpec,
    ObservationType,
)

from batches.specs import spec_to_dict
from demonstrations import Demonstration, read_demo
from learners.acting.factory import PolicyFactory
from learners.acting.numpy_policy import to_unity
from learners.host import checkpoint
from learners.networks.policies import ActorCritic
from rollout.environment.ports import PortAllocator, PortRange
from tests.driver.test_cli import cli
from tests.helpers import free_run
from unitysim.envs import load


def build_spec(env: str, index: int = 0) -> BehaviorSpec:
    """A unitysim behavior's spec, as the build announces it."""
    behavior = load(env).behaviors[index]
    observations = [
        ObservationSpec(
            s.shape,
            tuple(DimensionProperty(p) for p in s.dimension_properties),
            ObservationType(s.observation_type),
            s.name,
        )
        for s in behavior.sensors
    ]
    return BehaviorSpec(observations, ActionSpec(behavior.continuous, behavior.branches))


def write_checkpoint(path: Path, behaviors: dict[str, BehaviorSpec]) -> dict[str, ActorCritic]:
    """A checkpoint in the run's layout, each behavior a freshly seeded network."""
    factory = PolicyFactory(seed=3)
    networks = {name: factory.network(name, spec).eval() for name, spec in behaviors.items()}
    entries = {
        name: {
            "spec": spec_to_dict(net.spec),
            "network_settings": dataclasses.asdict(net.settings),
            "network": net.state_dict(),
            "algorithm": {},
        }
        for name, net in networks.items()
    }
    checkpoint.save(path, {"step": 1, "version": 1, "meta": {}, "behaviors": entries})
    return networks


def record(tmp_path: Path, *args: str, timeout: float = 120) -> tuple[int, str, str]:
    """Runs record-demo on its own ports and registry; checks every lease went back."""
    ports = PortRange(*free_run())
    result = cli(
        "record-demo",
        *args,
        timeout=timeout,
        UNITY_ROLLOUT_RUNTIME_DIR=str(tmp_path / "ports"),
        UNITY_ROLLOUT_PORT_RANGE=str(ports),
    )
    assert PortAllocator(ports, tmp_path / "ports").leases() == {}
    return result.returncode, result.stdout, result.stderr


def policy_action(network: ActorCritic, observations: tuple[np.ndarray, ...]) -> np.ndarray:
    obs = {
        n: torch.from_numpy(np.array(o[None]))
        for n, o in zip(network.sensor_names, observations, strict=True)
    }
    with torch.no_grad():
        continuous, _, _ = network.act(obs, None, deterministic=True)
    return to_unity(continuous.numpy()[0], network.settings)


@pytest.fixture(scope="module")
def ball_checkpoint(tmp_path_factory) -> tuple[Path, ActorCritic]:
    path = tmp_path_factory.mktemp("ckpt") / "checkpoints" / "3DBall" / "step-1.pt"
    networks = write_checkpoint(path, {"3DBall?team=0": build_spec("3DBall")})
    return path, networks["3DBall?team=0"]


def test_records_the_checkpoint_policy_as_unity_stores_actions(tmp_path, ball_checkpoint):
    path, network = ball_checkpoint
    out = tmp_path / "ball_expert_demo_long.demo"
    code, stdout, stderr = record(
        tmp_path, "--env", "unitysim:3DBall", "--checkpoint", str(path), "--steps", "300",
        "--out", str(out),
    )  # fmt: skip
    assert code == 0, stderr
    assert "300 steps of 3DBall?team=0" in stdout
    demo = read_demo(out, build_spec("3DBall"))
    assert (demo.meta.name, demo.meta.steps, len(demo.steps)) == ("ballexpertdemolo", 300, 300)
    assert demo.behavior_name == "3DBall?team=0"
    # Unity stores with each step the action of the agent's previous decision
    previous: dict[int, tuple[np.ndarray, ...]] = {}
    checked = 0
    for step in demo.steps:
        before = previous.pop(step.agent_id, None)
        if before is None:
            np.testing.assert_array_equal(step.continuous, np.zeros(2, np.float32))
        else:
            np.testing.assert_allclose(step.continuous, policy_action(network, before), atol=1e-5)
            checked += 1
        if not step.done:
            previous[step.agent_id] = step.observations
    assert checked > 250
    assert len({s.agent_id for s in demo.steps}) == 12  # every agent of the build
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_decided_actions_until_episodes_end(tmp_path, ball_checkpoint):
    path, network = ball_checkpoint
    out = tmp_path / "ball.demo"
    code, _, stderr = record(
        tmp_path, "--env", "unitysim:3DBall", "--checkpoint", str(path), "--episodes", "3",
        "--actions", "decided", "--out", str(out),
    )  # fmt: skip
    assert code == 0, stderr
    demo = read_demo(out, build_spec("3DBall"))
    assert sum(s.done for s in demo.steps) == 3 and demo.steps[-1].done
    assert demo.meta.episodes == 3
    for step in demo.steps[:200]:
        if not step.done:
            expected = policy_action(network, step.observations)
            np.testing.assert_allclose(step.continuous, expected, atol=1e-5)


def outcomes(demo: Demonstration) -> tuple[float, float]:
    """(success rate, mean return) of the episodes the demo ends."""
    returns, total, solved = [], {}, []
    for step in demo.steps:
        total[step.agent_id] = total.get(step.agent_id, 0.0) + step.reward
        if step.done:
            returns.append(total.pop(step.agent_id))
            solved.append(step.reward > 0.5)
    return float(np.mean(solved)), float(np.mean(returns))


def test_heuristic_hallway_expert_finds_the_matching_goal(tmp_path):
    out = tmp_path / "hallway.demo"
    code, _, stderr = record(
        tmp_path, "--env", "unitysim:Hallway", "--heuristic", "--episodes", "20", "--out", str(out)
    )
    assert code == 0, stderr
    demo = read_demo(out, build_spec("Hallway"))
    success, _ = outcomes(demo)
    assert success >= 0.8
    assert sum(s.done for s in demo.steps) == 20
    assert all(s.discrete.shape == (1,) and 0 <= s.discrete[0] < 5 for s in demo.steps)
    assert all(s.action_mask.shape in ((0,), (5,)) for s in demo.steps)


def test_heuristic_pyramids_expert_reaches_the_gold(tmp_path):
    out = tmp_path / "pyramids.demo"
    code, _, stderr = record(
        tmp_path, "--env", "unitysim:Pyramids", "--heuristic", "--episodes", "16", "--out", str(out)
    )
    assert code == 0, stderr
    success, mean_return = outcomes(read_demo(out, build_spec("Pyramids")))
    assert success >= 0.6 and mean_return >= 0.8  # random: about -0.95, almost never solved


def test_a_crash_while_recording_leaves_no_file(tmp_path, ball_checkpoint):
    out = tmp_path / "ball.demo"
    os.environ["UNITYSIM_CRASH_AFTER"] = "20"
    try:
        code, _, stderr = record(
            tmp_path, "--env", "unitysim:3DBall", "--checkpoint", str(ball_checkpoint[0]),
            "--steps", "5000", "--out", str(out),
        )  # fmt: skip
    finally:
        del os.environ["UNITYSIM_CRASH_AFTER"]
    assert code == 1
    lines = stderr.strip().splitlines()
    assert lines[-1].startswith("error: unitysim:3DBall failed while recording")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ports"]


def test_one_behavior_of_several_the_others_random(tmp_path):
    path = tmp_path / "striker.pt"
    write_checkpoint(path, {"Striker?team=0": build_spec("StrikersVsGoalie", 0)})
    out = tmp_path / "striker.demo"
    code, _, stderr = record(
        tmp_path, "--env", "unitysim:StrikersVsGoalie", "--checkpoint", str(path),
        "--behavior", "Striker", "--steps", "100", "--out", str(out),
    )  # fmt: skip
    assert code == 0, stderr
    demo = read_demo(out, build_spec("StrikersVsGoalie", 0))
    assert demo.behavior_name == "Striker?team=0" and demo.meta.steps == 100
    assert len({s.agent_id for s in demo.steps}) == 16  # the strikers; the goalies are not
    assert {s.group_id for s in demo.steps} != {0}  # their groups recorded


@pytest.mark.integration
def test_records_from_a_trained_run_directory(tmp_path):
    """A checkpoint as ``train`` writes it (per-behavior folders), named by its run."""
    trained = cli(
        "train", "--env", "unitysim:Basic", "--no-progress", "--max-steps", "300",
        "--results-dir", str(tmp_path / "results"), "--run-id", "tiny", "--workers", "1",
        "--cpus", "1", "--max-seconds", "120", timeout=300,
        UNITY_ROLLOUT_RUNTIME_DIR=str(tmp_path / "train-ports"),
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr[-3000:]
    out = tmp_path / "basic.demo"
    run = tmp_path / "results" / "tiny"
    code, _, stderr = record(
        tmp_path, "--env", "unitysim:Basic", "--checkpoint", str(run), "--steps", "50",
        "--out", str(out),
    )  # fmt: skip
    assert code == 0, stderr
    assert read_demo(out, build_spec("Basic")).meta.steps == 50
