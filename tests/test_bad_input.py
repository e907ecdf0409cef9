"""The mistakes a new user makes, each from a fresh directory: every one is a one-line
error naming what to fix (the last line of the output), with its exit code, no
traceback, no process left behind and no file that existed before changed. Most fail
before Ray starts; the ones that need Ray, a checkpoint or a player come last."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
import yaml

from driver import cli
from driver.declaration import from_arguments
from driver.options import TrainOptions
from driver.training.planner import plan
from tests.helpers import assert_run_gone

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parent.parent
BASIC = ["--env", "unitysim:Basic", "--no-progress", "--cpus", "1", "--workers", "1"]


def snapshot(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in root.rglob("*")
        if p.is_file()
    }


def run(cwd: Path, *argv: str, env: dict[str, str] | None = None, timeout: float = 240) -> str:
    """``unity-rollout ARGV`` in ``cwd``; its output, after checking that every process it
    started is gone."""
    marker = uuid.uuid4().hex
    result = subprocess.run(
        [sys.executable, "-m", "driver.cli", *argv],
        cwd=cwd,
        env={**os.environ, **(env or {}), "UNITY_ROLLOUT_TEST_RUN": marker},
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert_run_gone(marker, 30)
    return f"{result.returncode}\n{result.stdout}{result.stderr}"


def in_process(cwd: Path, *argv: str, env: dict[str, str] | None = None) -> str:
    """``unity-rollout ARGV`` called in this process, for the mistakes found before Ray
    starts (Ray's start fails the test): as ``run`` returns it, seconds sooner."""
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(cwd)
        for name, value in (env or {}).items():
            patch.setenv(name, value)
        patch.setattr("driver.local_ray.BackgroundRay", no_ray)
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = cli.main(list(argv))
            except SystemExit as exit:  # argparse's
                code = exit.code
    return f"{code}\n{out.getvalue()}{err.getvalue()}"


def no_ray(*args: object, **kwargs: object) -> None:
    raise AssertionError("Ray was started")


def check_error(
    cwd: Path, argv: list[str], code: int, fragment: str, before_ray: bool = False, **env: str
) -> str:
    before = snapshot(cwd)
    status, output = (in_process if before_ray else run)(cwd, *argv, env=env).split("\n", 1)
    lines = [line for line in output.splitlines() if line.strip()]
    assert "Traceback" not in output, output[-3000:]
    assert int(status) == code, output[-3000:]
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1 and lines[-1] == errors[0], output[-3000:]
    assert fragment in errors[0], errors[0]
    after = snapshot(cwd)
    assert {path: after.get(path) for path in before} == before, "a file changed"
    return errors[0]


@pytest.fixture
def fresh(tmp_path):
    (tmp_path / "bad.yaml").write_text("behaviors: [\n")
    (tmp_path / "typo.yaml").write_text(
        "behaviors:\n  Basic:\n    hyperparameters:\n      batchsize: 5\n"
    )
    (tmp_path / "type.yaml").write_text(
        "behaviors:\n  Basic:\n    hyperparameters:\n      learning_rate: fast\n"
    )
    (tmp_path / "NotExecutable.x86_64").write_text("#!/bin/sh\n")
    return tmp_path


BEFORE_RAY = [
    (["--config", "bad.yaml"], "bad.yaml: invalid YAML: line 2"),
    (["--config", "typo.yaml"], "batchsize: unknown key; did you mean 'batch_size'?"),
    (["--config", "type.yaml"], "learning_rate: expected a positive number, got 'fast'"),
    (["--config", "missing.yaml"], "missing.yaml: cannot read"),
    (["--config", "."], ".: cannot read"),
    (["--env", "./NoSuchBuild.x86_64"], "expected an executable ./NoSuchBuild.x86_64 ("),
    (["--env", "./NotExecutable.x86_64"], "run chmod +x on it"),
    (["--env", "editor", "--workers", "2"], "there is one editor (port 5004)"),
    (["--max-steps", "-1"], "--max-steps: at least 1, got -1"),
    (["--max-steps", "abc"], "argument --max-steps: invalid int value: 'abc'"),
    (["--num-areas", "0"], "--num-areas: at least 1, got 0"),
    (["--workers", "0"], "--workers: at least 1, got 0"),
    (["--workers", "many"], "a number or auto, not 'many'"),
    (["--max-seconds", "-3"], "--max-seconds: positive, got -3"),
    (["--timeout-wait", "0"], "--timeout-wait: at least 1, got 0"),
    (["--run-id", "../escape", "--results-dir", "sub"], "--run-id: one directory name"),
    (["--run-id", "a/b"], "--run-id: one directory name"),
    (["--run-id", "."], "--run-id: one directory name"),
    (["--device", "tpu"], "'tpu': use"),
    (["--resume"], "--resume: no checkpoint in results/run/checkpoints"),
    (["--no-such-flag"], "unrecognized arguments: --no-such-flag"),
]


@pytest.mark.parametrize(("argv", "fragment"), BEFORE_RAY, ids=lambda v: str(v)[:40])
def test_a_bad_option_or_config_is_one_line_before_ray(fresh, argv, fragment):
    check_error(fresh, ["train", *argv], 2, fragment, before_ray=True)
    assert not (fresh / "escape").exists() and not (fresh / "results").exists()


@pytest.mark.parametrize(
    ("value", "fragment"),
    [("abc", "invalid port range 'abc'"), ("80-90", "invalid port range 80-90")],
)
def test_a_bad_port_range_is_one_line_before_ray(fresh, value, fragment):
    message = check_error(
        fresh, ["train"], 2, fragment, before_ray=True, UNITY_ROLLOUT_PORT_RANGE=value
    )
    assert message.startswith("error: UNITY_ROLLOUT_PORT_RANGE: ")


def test_a_port_registry_that_cannot_be_written_is_one_line_before_ray(fresh):
    (fresh / "a-file").write_text("")
    fragment = "UNITY_ROLLOUT_RUNTIME_DIR: cannot create a-file/registry"
    env = {"UNITY_ROLLOUT_RUNTIME_DIR": "a-file/registry"}
    check_error(fresh, ["train"], 2, fragment, before_ray=True, **env)


@pytest.mark.parametrize("bad", ["missing.pt", "empty", "corrupt.pt"])
def test_export_of_a_bad_source_names_it(fresh, bad):
    (fresh / "empty").mkdir()
    (fresh / "corrupt.pt").write_bytes(b"PK\x03\x04 cut short")
    check_error(fresh, ["export", bad], 2, bad, before_ray=True)


# ---- with Ray, players and checkpoints ------------------------------------------------


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """One short real run of Basic: its results directory, to copy into each test."""
    root = tmp_path_factory.mktemp("trained")
    output = run(root, "train", *BASIC, "--max-steps", "300", "--run-id", "run")
    assert output.startswith("0\n"), output[-3000:]
    return root / "results"


@pytest.fixture
def with_run(fresh, trained):
    shutil.copytree(trained, fresh / "results")
    return fresh


def test_an_existing_run_is_not_overwritten(with_run):
    check_error(with_run, ["train", *BASIC], 2, "already holds a run: pass --resume", True)


def test_resume_with_another_network_names_the_setting_and_changes_nothing(with_run):
    config = yaml.safe_load((ROOT / "config/Basic.yaml").read_text())
    config["behaviors"]["Basic"]["network_settings"]["hidden_units"] = 64
    (with_run / "wider.yaml").write_text(yaml.safe_dump(config))
    argv = ["train", *BASIC, "--resume", "--config", "wider.yaml"]
    message = check_error(with_run, argv, 2, "network_settings.hidden_units 20, the config", True)
    assert "configuration.yaml" in message  # where the settings it was trained with are


def test_initializing_from_a_run_of_another_network_names_the_setting(with_run):
    config = yaml.safe_load((ROOT / "config/Basic.yaml").read_text())
    config["behaviors"]["Basic"]["network_settings"]["num_layers"] = 2
    (with_run / "deeper.yaml").write_text(yaml.safe_dump(config))
    argv = ["train", *BASIC, "--config", "deeper.yaml", "--run-id", "new"]
    argv += ["--initialize-from", "run"]
    fragment = "--initialize-from: Basic was trained with network_settings.num_layers 1"
    check_error(with_run, argv, 2, fragment, before_ray=True)


def with_init_path(root: Path, init_path: str, **network: int) -> str:
    """config/Basic.yaml with behaviors.Basic.init_path (and network changes); its file."""
    config = yaml.safe_load((ROOT / "config/Basic.yaml").read_text())
    config["behaviors"]["Basic"]["init_path"] = init_path
    config["behaviors"]["Basic"]["network_settings"].update(network)
    (root / "init.yaml").write_text(yaml.safe_dump(config))
    return "init.yaml"


@pytest.mark.parametrize(
    ("init_path", "network", "fragment"),
    [
        ("results/nothing.pt", {}, "behaviors.Basic.init_path: no checkpoint at results/nothing"),
        (
            "results/run/checkpoints/Basic_team0",
            {"num_layers": 2},
            "behaviors.Basic.init_path: Basic was trained with network_settings.num_layers 1",
        ),
    ],
    ids=["missing", "another network"],
)
def test_an_init_path_that_cannot_start_the_behavior_is_one_line(
    with_run, init_path, network, fragment
):
    config = with_init_path(with_run, init_path, **network)
    argv = ["train", *BASIC, "--config", config, "--run-id", "new"]
    check_error(with_run, argv, 2, fragment, before_ray=True)


@pytest.mark.parametrize("how", ["folder", "file", "file name with --initialize-from"])
def test_a_behavior_starts_from_its_init_path_as_mlagents_learn(with_run, how):
    """ML-Agents' per-behavior ``init_path``: a checkpoint file or folder, or with
    ``--initialize-from`` a file name in that run's folder of the behavior. The run
    starts from those networks (none of their steps)."""
    from driver.training.planner import open_run
    from learners.host import checkpoint

    folder = with_run / "results/run/checkpoints/Basic_team0"
    file = checkpoint.newest_first(folder)[0]
    init_path = {"folder": str(folder), "file": str(file)}.get(how, file.name)
    config = with_init_path(with_run, init_path)
    argv = ["train", *BASIC, "--config", str(with_run / config), "--run-id", "new"]
    argv += ["--results-dir", str(with_run / "results")]
    if how.endswith("--initialize-from"):
        argv += ["--initialize-from", "run"]
    start = open_run(plan(from_arguments(TrainOptions, cli.build_parser().parse_args(argv))))
    assert start.resume is None and start.initial is not None
    entry = start.initial["behaviors"]["Basic?team=0"]
    saved = checkpoint.read(file)["behaviors"]["Basic?team=0"]
    for name, tensor in saved["network"].items():
        assert (entry["network"][name] == tensor).all(), name


def test_and_initialized_from_a_fitting_run_it_plays_its_policy_in_inference(with_run):
    """What the mistake above was about, done right: the workers play the other run's
    policy, train nothing and write no checkpoint. The other run's policy is made
    unmistakable first: it always walks right, so every episode returns Basic's best, 0.93
    in 7 steps; the factory's random weights would not."""
    import torch

    from learners.host import checkpoint

    (saved,) = (with_run / "results/run/checkpoints/Basic_team0").glob("*.pt")
    state = checkpoint.read(saved)
    network = state["behaviors"]["Basic?team=0"]["network"]
    network["logits.weight"].zero_()
    network["logits.bias"].copy_(torch.tensor([0.0, 0.0, 30.0]))  # stay, left, right
    checkpoint.save(saved, state)
    argv = [*BASIC, "--run-id", "new", "--initialize-from", "run", "--inference"]
    # past config/Basic.yaml's summary_freq (2,000): the summary reads its episodes
    status, output = run(with_run, "train", *argv, "--max-steps", "2100").split("\n", 1)
    assert status == "0" and output.splitlines()[-1].endswith("no checkpoint"), output[-3000:]
    assert not (with_run / "results/new/checkpoints").exists()
    summary = json.loads((with_run / "results/new/summary.json").read_text())
    assert summary["steps"] >= 2100 and summary["version"] == 1 and summary["checkpoint"] is None
    played = summary["behaviors"]["Basic?team=0"]
    assert played["episode_length"] == 7 and played["mean_reward"] == pytest.approx(0.93), played


def test_resume_on_corrupt_checkpoints_names_the_file(with_run):
    for path in (with_run / "results/run/checkpoints").rglob("*.pt"):
        path.write_bytes(path.read_bytes()[:10])  # a kill mid-write of an unsafe writer
    check_error(with_run, ["train", *BASIC, "--resume"], 2, "no readable checkpoint", True)


def test_resume_falls_back_to_the_newest_intact_checkpoint_and_says_so(with_run):
    folder = with_run / "results/run/checkpoints/Basic_team0"
    (newest,) = folder.glob("*.pt")
    older = folder / "step-0000000001.pt"
    shutil.copy2(newest, older)
    os.utime(older, ns=(newest.stat().st_mtime_ns - 10**9,) * 2)
    newest.write_bytes(newest.read_bytes()[:10])
    status, output = run(with_run, "train", *BASIC, "--resume", "--max-steps", "400").split("\n", 1)
    assert status == "0", output[-3000:]
    assert f"{newest.relative_to(with_run)}: unreadable checkpoint" in output
    assert f"using {older.relative_to(with_run)}" in output


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["--env", "unitysim:NoSuchEnv"], "NoSuchEnv"),
        (["--device", "cuda"], "--device cuda: the Ray cluster has no GPU"),
    ],
)
def test_what_needs_ray_to_check_is_still_one_line(fresh, argv, fragment):
    if argv[-1] == "cuda" and shutil.which("nvidia-smi"):
        pytest.skip("this machine has a GPU")
    check_error(fresh, ["train", *BASIC, *argv], 2, fragment)


def test_a_build_that_exits_at_once_leaves_nothing_that_blocks_a_retry(fresh):
    build = fresh / "Exits.x86_64"
    build.write_text("#!/bin/sh\nexit 3\n")
    build.chmod(0o755)
    argv = ["train", *BASIC, "--env", str(build)]
    message = check_error(fresh, argv, 1, "nothing was trained and no checkpoint written")
    assert "Player-0.log" not in message  # it died before writing one
    with pytest.MonkeyPatch.context() as patch:  # the same command again passes its checks
        patch.chdir(fresh)
        plan(from_arguments(TrainOptions, cli.build_parser().parse_args(argv)))


def test_a_build_that_never_connects_is_one_line(fresh):
    build = fresh / "Silent.x86_64"
    build.write_text("#!/bin/sh\nsleep 600\n")
    build.chmod(0o755)
    argv = ["train", *BASIC, "--env", str(build), "--timeout-wait", "1"]
    check_error(fresh, argv, 1, "did not connect within timeout_wait (1 s); it wrote no log")


def test_a_port_range_too_small_names_what_holds_its_ports(fresh):
    argv = ["train", *BASIC, "--workers", "2", "--cpus", "2"]
    fragment = "no free port in 24990-24990 (1 ports): 1 leased"
    message = check_error(fresh, argv, 1, fragment, UNITY_ROLLOUT_PORT_RANGE="24990-24990")
    assert "0 in quarantine" in message


def test_a_behavior_the_learner_cannot_train_is_one_line(fresh):
    """A buffer_size the learner's memory cannot hold (known only once the build's
    observations are): the learner's refusal ends the run in one line, not a traceback."""
    config = "behaviors:\n  Basic:\n    hyperparameters: {buffer_size: 100000000000}\n"
    (fresh / "huge.yaml").write_text(config)
    argv = ["train", *BASIC, "--config", "huge.yaml"]
    check_error(fresh, argv, 1, "the learner: MemoryError: behavior Basic: buffer_size")
