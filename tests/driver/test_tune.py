"""``unity-rollout tune``: the search file's checks (one line before Ray starts), and a
4-trial PBT on 2 cores on a step budget: every trial a full run, an exploit through
another trial's checkpoint with its optimizer state, no port clash, no process left and
every stretch of every trial with its sample ledger balanced."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
import torch
import yaml

from driver.declaration import TrainingError
from driver.options import TrainOptions, TuneOptions
from driver.tuning.search import with_values
from driver.tuning.tune import plan_tune
from learners.trainer_config.parse import parse_config
from rollout.environment.ports import PortAllocator
from tests.helpers import assert_run_gone
from tests.waiting import poll_until

CONFIG = {
    "behaviors": {
        "3DBall": {
            "trainer_type": "ppo",
            "hyperparameters": {"batch_size": 128, "buffer_size": 500, "num_epoch": 2},
            "network_settings": {"hidden_units": 32, "num_layers": 1},
            "time_horizon": 64,
            "summary_freq": 500,
            "checkpoint_interval": 100000,
        }
    }
}
LR = "behaviors.3DBall.hyperparameters.learning_rate"


def write(path: Path, data: object) -> Path:
    path.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return path


def planned(tmp_path: Path, search: object, **tuning: object):
    config = write(tmp_path / "config.yaml", CONFIG)
    options = TrainOptions(config=str(config), results_dir=str(tmp_path / "results"))
    return plan_tune(options, TuneOptions(search=str(write(tmp_path / "s.yaml", search)), **tuning))


def test_with_values_sets_dotted_keys_and_makes_sections():
    data = with_values(CONFIG, {LR: 0.01, "default_settings.hyperparameters.beta": 0.002})
    assert data["behaviors"]["3DBall"]["hyperparameters"]["learning_rate"] == 0.01
    assert data["behaviors"]["3DBall"]["hyperparameters"]["batch_size"] == 128
    assert data["default_settings"] == {"hyperparameters": {"beta": 0.002}}
    assert "learning_rate" not in CONFIG["behaviors"]["3DBall"]["hyperparameters"]  # a copy
    config = parse_config(data)
    assert config.for_behavior("3DBall").hyperparameters.learning_rate == 0.01


def test_a_search_plans_with_its_domains(tmp_path):
    plan = planned(tmp_path, {LR: {"loguniform": [1e-4, 1e-2]}, "behaviors.3DBall.max_steps": 4000})
    assert [d.domain for d in plan.search.dimensions] == ["loguniform", "choice"]
    assert plan.metric_behavior == "3DBall"
    assert plan.report_every == 500  # the behavior's summary_freq
    assert set(plan.search.space()) == {LR, "behaviors.3DBall.max_steps"}


@pytest.mark.parametrize(
    ("search", "message"),
    [
        ({"behaviors.3DBall.hyperparameters.learnig_rate": {"choice": [1e-3]}}, "learnig_rate"),
        ({LR: {"loguniform": [0, 1e-2]}}, "loguniform needs low > 0"),
        ({LR: {"uniform": [1e-2, 1e-3]}}, "low < high"),
        ({LR: {"normal": [1e-3, 1e-4]}}, "one of choice, uniform"),
        ({"behaviors.3DBall.hyperparameters.lambd": {"uniform": [0.9, 1.5]}}, "in [0, 1]"),
        ({"behaviors.3DBal.hyperparameters.beta": {"choice": [1e-3]}}, "no behavior '3DBal'"),
        ({"behaviors.3DBall.network_settings.hidden_units": {"choice": [32, 64]}}, "PBT"),
        ({LR: {"grid": [1e-3, 3e-3]}}, "grid under PBT"),
        ([1, 2], "a mapping of trainer-config keys"),
    ],
)
def test_a_bad_search_is_one_line_naming_the_key(tmp_path, search, message):
    with pytest.raises(TrainingError) as error:
        planned(tmp_path, search)
    assert message in str(error.value)
    assert "\n" not in str(error.value)


def test_network_keys_and_grids_are_searched_without_pbt(tmp_path):
    search = {"behaviors.3DBall.network_settings.hidden_units": {"grid": [32, 64]}}
    assert planned(tmp_path, search, scheduler="asha").search.dimensions[0].domain == "grid"


def test_options_a_tune_cannot_honour_are_errors(tmp_path):
    config = write(tmp_path / "config.yaml", CONFIG)
    search = str(write(tmp_path / "s.yaml", {LR: {"choice": [1e-3]}}))
    for given, flag in (({"resume": True}, "--resume"), ({"workers": "auto"}, "--workers auto")):
        options = TrainOptions(config=str(config), results_dir=str(tmp_path), **given)
        with pytest.raises(TrainingError, match=flag):
            plan_tune(options, TuneOptions(search=search))
    with pytest.raises(TrainingError, match="--search: required"):
        TuneOptions().validate()
    with pytest.raises(TrainingError, match=r"--quantile-fraction: in \(0, 0.5\], got 0.7"):
        TuneOptions(search=search, quantile_fraction=0.7).validate()


@pytest.mark.parametrize(
    ("given", "tuning", "pauses"),
    [
        ({}, {"trials": 4}, False),  # local, every trial at once: a trial stops only to exploit
        ({}, {"trials": 4, "concurrent_trials": 2}, True),  # two wait their turn
        ({"address": "auto"}, {"trials": 4}, True),  # a cluster's size is not known here
    ],
)
def test_pbt_pauses_for_turns_only_where_trials_wait_for_them(tmp_path, given, tuning, pauses):
    from ray.tune.schedulers import PopulationBasedTraining

    from driver.tuning.pbt import AllAtOncePBT
    from driver.tuning.tune import _scheduler

    plan = planned(tmp_path, {LR: {"loguniform": [1e-4, 1e-2]}}, **tuning)
    plan = dataclasses.replace(plan, options=dataclasses.replace(plan.options, **given))
    scheduler = _scheduler(plan)
    assert isinstance(scheduler, PopulationBasedTraining)
    assert isinstance(scheduler, AllAtOncePBT) is not pauses


def test_an_existing_tune_run_is_not_overwritten_without_force(tmp_path):
    (tmp_path / "results" / "run" / "trials").mkdir(parents=True)
    with pytest.raises(TrainingError, match="--force"):
        planned(tmp_path, {LR: {"choice": [1e-3]}})


PBT_SAFETY_STOP_S = 1500  # ~100 s alone on a slow 2-core machine, 1,205 s once beside the suite


@pytest.mark.timeout(PBT_SAFETY_STOP_S + 90)  # pytest's 300 s fired first on a busy CI machine
def test_pbt_with_four_trials_on_two_cores(tmp_path):
    """Steps: 4 trials x 8,000; PBT perturbs at every report and the worse half exploits.
    A report comes at the first turn of the run's loop past 500 steps, about 1,000 steps
    here, so each trial gets 5-8 rounds. Ray's asynchronous PBT exploits only where a
    better trial saved a checkpoint at an earlier perturbation of its own: at 4,000 steps
    (3-4 rounds) a CI run had none; at 12,000 runs had 6, 7 and 13, but one took more
    than 600 s on a slower 2-core machine beside the rest of the suite."""
    write(tmp_path / "config.yaml", CONFIG)
    write(tmp_path / "search.yaml", {LR: {"loguniform": [1e-4, 3e-3]}})
    registry = tmp_path / "ports"
    marker = uuid.uuid4().hex
    command = [
        sys.executable, "-m", "driver.cli", "tune", "config.yaml", "--search", "search.yaml",
        "--trials", "4", "--workers", "1", "--cpus", "2", "--max-steps", "8000",
        "--perturbation-interval", "500", "--quantile-fraction", "0.5",
        "--run-id", "pbt", "--seed", "3",
    ]  # fmt: skip
    env = {
        **os.environ,
        "UNITY_ROLLOUT_TEST_RUN": marker,
        "UNITY_ROLLOUT_RUNTIME_DIR": str(registry),
    }
    ports = PortAllocator(registry_dir=registry)
    most_at_once = 0  # Unity instances holding a lease at one time, over all trials
    process = subprocess.Popen(
        command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    try:

        def ended() -> bool:  # sampled at each look: the most leases held at once
            nonlocal most_at_once
            most_at_once = max(most_at_once, len(ports.leases()))
            return process.poll() is not None

        poll_until(ended, PBT_SAFETY_STOP_S, every=0.5)
        output = process.communicate(timeout=5)[0]
    finally:
        if process.poll() is None:
            process.kill()
        assert_run_gone(marker, 60)  # Ray, trials, workers and players all gone
    assert process.returncode == 0, output[-3000:]
    assert "tune finished: 4 trials (0 failed)" in output
    assert most_at_once == 4, "the four trials' instances held their ports side by side"
    root = tmp_path / "results" / "pbt"
    with open(root / "trials.csv") as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 4
    exploited = 0
    for row in rows:
        assert int(row["steps"]) >= 8000 and row["error"] == ""
        run_dir = Path(row["run_dir"])
        pieces = sorted((run_dir / "pieces").glob("*.json"))
        assert pieces, f"{run_dir}: no stretch ended as a run ends"
        for piece in pieces:
            summary = json.loads(piece.read_text())
            assert summary["ledger"]["balanced"], piece
            ledger = summary["ledger"]
            assert ledger["produced"] == ledger["delivered"] + sum(ledger["dropped"].values())
            assert summary["faults"]["unity_restarts"] == 0, piece  # a port clash would be one
        for restored in (run_dir / "restored").glob("*/*.pt"):
            state = torch.load(restored, weights_only=True)
            (entry,) = state["behaviors"].values()
            assert entry["algorithm"]["optimizer"]["state"], "the optimizer's moments travel"
        restores = (run_dir / "restores.jsonl").read_text().splitlines() if pieces[1:] else []
        assert len(restores) == len(pieces) - 1  # every later stretch began at a checkpoint
        sources = [json.loads(line)["from"] for line in restores]
        # every trial runs at once: none is paused to give another a turn (driver/tuning/pbt.py)
        assert run_dir.name not in sources, f"{run_dir.name} paused and resumed: {sources}"
        exploited += len(sources)
    print("stretches begun at another trial's checkpoint:", exploited)
    assert exploited >= 1, "no trial took another's checkpoint"
    best = yaml.safe_load((root / "best.yaml").read_text())
    best_lr = best["behaviors"]["3DBall"]["hyperparameters"]["learning_rate"]
    assert any(float(row[LR]) == best_lr for row in rows)
    parse_config(best)


def test_without_ray_tune_the_command_says_how_to_get_it(tmp_path, monkeypatch, capsys):
    import importlib.util

    from driver import cli

    write(tmp_path / "config.yaml", CONFIG)
    write(tmp_path / "search.yaml", {LR: {"choice": [1e-3]}})
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "pyarrow" else real(name, *a)
    )
    monkeypatch.chdir(tmp_path)
    assert cli.main(["tune", "config.yaml", "--search", "search.yaml"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: tune needs Ray Tune: pip install 'unity-rollout[tune]'")
    assert "\n" not in err
