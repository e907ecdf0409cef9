"""The main job end to end, in local 2-core mode on unitysim 3DBall: a short run learns
(clearly beats the random policy), resume continues the step count, the trained policy
exports to ONNX and runs in onnxruntime, and SIGINT/SIGTERM stop a run with a final
checkpoint and no process left."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import onnxruntime as ort
import psutil
import pytest
import torch

from driver.options import TrainingError, TrainOptions
from driver.training.train import train
from learners.host import checkpoint
from learners.host.export import export_checkpoint
from tests.conftest import tagged_processes
from tests.helpers import assert_run_gone, kill_run, run_marked, start_train_cli
from tests.waiting import wait_for

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def trained(ray_session, tmp_path_factory):
    results = tmp_path_factory.mktemp("results")
    options = TrainOptions(
        results_dir=str(results), run_id="ball", max_steps=42_000, progress=False
    )
    return options, train(options)


def _drops_per_agent_decision(run_checkpoint: str | None, decisions: int = 300) -> float:
    """How often 3DBall's agents drop the ball under the run's policy, its actions sampled
    as Unity's inference samples them by default (None: random actions), on a fresh
    unitysim build. The run's last summary cannot tell: once the ball stays up, no episode
    ends, and the summary before it may be thousands of steps of learning old."""
    from mlagents_envs.base_env import ActionTuple

    from rollout.environment.unity import UnityConfig, UnityInstance

    network = None
    if run_checkpoint is not None:
        network = checkpoint.networks(checkpoint.load(run_checkpoint))["3DBall?team=0"]
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    drops = agent_decisions = 0
    with UnityInstance(UnityConfig("unitysim:3DBall", seed=5)) as unity:
        unity.reset()
        for _ in range(decisions):
            deciding, ended = unity.get_steps("3DBall?team=0")
            drops += int((~ended.interrupted).sum())
            agent_decisions += len(deciding)
            obs = deciding.obs[0].astype(np.float32)
            if network is None:
                action = rng.uniform(-1, 1, size=(len(deciding), 2)).astype(np.float32)
            else:
                with torch.no_grad():
                    sampled, _, _ = network.act({network.sensor_names[0]: torch.from_numpy(obs)})
                action = network.unity_action(sampled).numpy()
            unity.set_actions("3DBall?team=0", ActionTuple(continuous=action))
            unity.step()
    return drops / agent_decisions


def test_a_short_run_beats_the_random_policy(trained):
    _, result = trained
    random_rate = _drops_per_agent_decision(None)
    trained_rate = _drops_per_agent_decision(str(result.checkpoint))
    assert random_rate > 1 / 40, random_rate  # about 20 decisions to a drop
    assert trained_rate < random_rate / 5, (trained_rate, random_rate)
    summary = json.loads((result.run_dir / "summary.json").read_text())
    assert summary["steps"] >= 42_000 and summary["interrupted"] is None
    ledger = summary["ledger"]  # no fault: nothing dropped but what the end cut off
    assert ledger["balanced"] and ledger["delivered"] >= 42_000, ledger
    assert {r: n for r, n in ledger["dropped"].items() if n} == {
        "shutdown": ledger["produced"] - ledger["delivered"]
    }
    events = list((result.run_dir / "3DBall").glob("events.out.tfevents.*"))
    assert events, "TensorBoard events per behavior"
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tags = EventAccumulator(str(events[0].parent)).Reload().Tags()["scalars"]
    for tag in (
        "Environment/Cumulative Reward",
        "Environment/Episode Length",
        "Policy/Extrinsic Reward",
        "Losses/Policy Loss",
        "Losses/Value Loss",
        "Policy/Entropy",
        "Policy/Learning Rate",
        "Health/Policy Lag",
        "Perf/Agent Steps per Second",
    ):
        assert tag in tags, tag


def test_resume_continues_the_step_count(trained, ray_session):
    options, first = trained
    with pytest.raises(TrainingError, match="--resume"):
        train(options)  # the run exists: refuse to overwrite it silently
    resumed = train(
        TrainOptions(
            results_dir=options.results_dir,
            run_id=options.run_id,
            resume=True,
            max_steps=54_000,
            progress=False,
        )
    )
    steps, first_steps = sum(resumed.steps.values()), sum(first.steps.values())
    assert 54_000 <= steps < first_steps + 24_000, "continued from the checkpoint, not from 0"
    assert resumed.version > first.version
    assert checkpoint.load(resumed.checkpoint)["step"] == steps
    with pytest.raises(TrainingError, match="no checkpoint"):
        train(TrainOptions(results_dir=options.results_dir, run_id="nothing", resume=True))


def learners() -> list[int]:
    """This session's learner actors' processes."""
    found = []
    for process in tagged_processes(include_ray=True):
        with contextlib.suppress(psutil.Error):
            if "ray::RayLearner" in " ".join(process.cmdline()):
                found.append(process.pid)
    return found


def test_a_finished_run_ends_its_learner(trained, ray_session):
    """After the runs above, the session's Ray holds none of their learners: a caller that
    trains again in the same Ray (a Tune trial's next stretch, a notebook) keeps no idle
    learner holding a replay buffer."""
    wait_for(lambda: not learners(), "the finished runs' learners to end", seconds=60)


def test_the_trained_policy_exports_and_runs_in_onnxruntime(trained, tmp_path):
    _, result = trained
    (path,) = export_checkpoint(result.checkpoint, tmp_path)
    network = checkpoint.networks(checkpoint.load(result.checkpoint))["3DBall?team=0"]
    obs = np.random.default_rng(0).normal(size=(5, 8)).astype(np.float32)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (actions,) = session.run(["deterministic_continuous_actions"], {"obs_0": obs})
    with torch.no_grad():
        expected, _, _ = network.act({network.sensor_names[0]: torch.from_numpy(obs)}, None, True)
    np.testing.assert_allclose(actions, network.unity_action(expected).numpy(), atol=1e-5)


def _connections(process: psutil.Process) -> list:
    try:
        return process.net_connections(kind="inet")
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return []


@pytest.mark.parametrize("how", ["SIGTERM to the driver", "SIGINT to the process group"])
def test_a_signal_stops_the_run_with_a_final_checkpoint(tmp_path, how):
    marker = uuid.uuid4().hex
    driver = start_train_cli(marker, "--results-dir", str(tmp_path), "--max-seconds", "300")
    try:
        run_dir = Path(tmp_path) / "run"

        def begun() -> bool:  # training has begun: its first events file
            assert driver.poll() is None, driver.stdout.read() if driver.stdout else ""
            return bool(list((run_dir / "3DBall").glob("events.*")))

        wait_for(begun, "training's first events file", 240)
        listening = {
            f"{c.laddr.ip}:{c.laddr.port}"
            for p in run_marked(marker)
            for c in _connections(p)
            if c.status == psutil.CONN_LISTEN
        }
        assert listening, "the run's Ray and Unity processes listen somewhere"
        exposed = sorted(a for a in listening if not a.startswith(("127.", "::1", "::ffff:127.")))
        assert not exposed, f"local mode must bind loopback only: {exposed}"
        if how.startswith("SIGTERM"):
            driver.send_signal(signal.SIGTERM)
        else:
            os.killpg(driver.pid, signal.SIGINT)
        output, _ = driver.communicate(timeout=90)
        assert driver.returncode == 0, output[-2000:]
        summary = json.loads((run_dir / "summary.json").read_text())
        assert summary["interrupted"] == how.split()[0]
        final = checkpoint.load(summary["checkpoint"])
        assert final["step"] == summary["steps"] > 0
    finally:
        kill_run(driver)
    assert_run_gone(marker, 30)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (TrainOptions(env="editor", workers=2), "--workers 1"),
        (TrainOptions(workers=0), "--workers: at least 1, got 0"),
        (TrainOptions(env="/nonexistent/Game.x86_64"), "/nonexistent/Game"),
        (TrainOptions(config="/nonexistent.yaml"), "/nonexistent.yaml"),
        (TrainOptions(config="/"), "/: cannot read"),  # a directory
        (TrainOptions(timeout_wait=0), "--timeout-wait: at least 1"),
        (TrainOptions(max_steps=-1), "--max-steps: at least 1, got -1"),
        (TrainOptions(num_areas=0), "--num-areas: at least 1, got 0"),
        (TrainOptions(run_id="../escape"), "--run-id: one directory name"),
        (TrainOptions(run_id="a/b"), "--run-id: one directory name"),
        (TrainOptions(run_id="."), "--run-id: one directory name"),
        (TrainOptions(workers=2, max_workers=4), "--max-workers: a number of at least 1, with"),
        (TrainOptions(workers="auto", max_workers=0), "--max-workers: a number of at least 1"),
    ],
)
def test_bad_options_are_one_line_errors_before_anything_starts(options, message, tmp_path):
    options = dataclasses.replace(options, results_dir=str(tmp_path))
    with pytest.raises(TrainingError, match=re.escape(message)) as error:
        train(options)
    assert "\n" not in str(error.value)
    assert not list(tmp_path.iterdir()), "nothing written for a run that could not start"


def test_a_results_dir_that_cannot_be_written_is_a_one_line_error(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    options = TrainOptions(env="unitysim:Basic", results_dir=str(blocker / "results"))
    with pytest.raises(TrainingError, match=r"--results-dir: cannot write .*a-file/results/run"):
        train(options)


def test_workers_auto_fills_the_cluster(ray_session, tmp_path):
    """The test session's Ray has 2 CPUs: with none left to the learner, 2 workers."""
    options = TrainOptions(
        env="unitysim:Basic",
        results_dir=str(tmp_path),
        workers="auto",
        learner_cpus=0.0,
        max_steps=1500,
        progress=False,
    )
    result = train(options)
    summary = json.loads((result.run_dir / "summary.json").read_text())
    assert summary["membership"] == {"added": 0, "removed": 0, "live": 2}
    assert set(summary["ledger"]["workers"]) == {"0", "1"} and summary["ledger"]["balanced"]


def test_engine_settings_reach_the_unity_config(tmp_path):
    from driver.system import unity_config
    from learners.trainer_config.parse import parse_config

    config = parse_config({"engine_settings": {"time_scale": 5, "no_graphics": False}})
    unity = unity_config(TrainOptions(), config, tmp_path)
    assert unity.engine.time_scale == 5 and unity.no_graphics is False


def test_restart_limits_and_timeout_reach_every_unity_instance(tmp_path):
    from driver.system import unity_config
    from driver.training.planner import load_run_config
    from rollout.environment.restarts import RestartPolicy

    options = TrainOptions(env="unitysim:Basic", restarts_rate_limit_n=3, timeout_wait=7)
    unity = unity_config(options, load_run_config(options), tmp_path)
    assert unity.restarts == RestartPolicy(rate_limit_n=3) and unity.timeout_wait == 7


def test_two_runs_on_one_node_share_the_port_registry(tmp_path):
    """Two `unity-rollout train` at once, each with its own local Ray: four Unity
    instances, four distinct ports from the one registry, no instance restarted (a port
    clash would have cost a restart, and a quarantined port more)."""
    from rollout.environment.ports import REGISTRY_VARIABLE, PortAllocator

    registry = tmp_path / "registry"
    marker = uuid.uuid4().hex
    env = {**os.environ, REGISTRY_VARIABLE: str(registry), "UNITY_ROLLOUT_TEST_RUN": marker}
    command = [sys.executable, "-m", "driver.cli", "train", "--env", "unitysim:Basic"]
    command += ["--no-progress", "--max-steps", "2000", "--results-dir", str(tmp_path)]
    command += ["--cpus", "1", "--max-seconds", "300"]
    runs = [
        subprocess.Popen(
            [*command, "--run-id", f"run{index}"],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        for index in range(2)
    ]
    try:
        outputs = [run.communicate(timeout=600)[0].decode() for run in runs]
    finally:
        for run in runs:
            if run.poll() is None:
                os.killpg(run.pid, signal.SIGKILL)
                run.wait()
    assert [run.returncode for run in runs] == [0, 0], outputs
    ports = PortAllocator(registry_dir=registry).quarantined()
    assert len(ports) == 4, ports
    wait_for(lambda: not run_marked(marker), "the runs' processes to end", 60)


def test_cuda_on_a_cluster_without_a_gpu_is_one_line_before_any_worker(ray_session, tmp_path):
    """The session's Ray has no GPU (nor has CI): asking the learner for one stops the
    run before a worker or a Unity player starts."""
    import ray

    if ray.cluster_resources().get("GPU", 0):
        pytest.skip("this cluster has a GPU: the refusal needs one without")
    options = TrainOptions(env="unitysim:3DBall", results_dir=str(tmp_path), device="cuda")
    with pytest.raises(TrainingError) as error:
        train(options)
    message = str(error.value)
    assert "\n" not in message and message.startswith("--device cuda: the Ray cluster has no GPU")
    assert not (tmp_path / "run" / "unity-logs").exists() or not any(
        (tmp_path / "run" / "unity-logs").iterdir()
    )


def test_mixed_precision_the_learner_cannot_use_is_said_in_the_driver(
    ray_session, tmp_path, caplog
):
    """The learner runs in a Ray actor whose log does not reach the user: where its CPU
    emulates bfloat16 it computes in float32, and the driver's log says so once; where
    bfloat16 is native, nothing is said and the run trains in it."""
    from learners.host.devices import bfloat16_slow

    why = bfloat16_slow(torch.device("cpu"))
    options = TrainOptions(
        env="unitysim:Basic", results_dir=str(tmp_path), run_id="mixed", max_steps=1_000,
        mixed_precision=True, progress=False, device="cpu",
    )  # fmt: skip
    with caplog.at_level("WARNING", logger="driver.training.behavior_notes"):
        result = train(options)
    assert sum(result.steps.values()) >= 1_000
    said = [r.getMessage() for r in caplog.records if "--mixed-precision" in r.getMessage()]
    if why is None:
        assert said == []
    else:
        assert said == [
            f"--mixed-precision: {why}, where bfloat16 runs slower than float32; the learner "
            "computes in float32"
        ]
