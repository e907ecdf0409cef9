"""Per-behavior keys stay per behavior: each behavior checkpoints at its own interval and
keeps its own count, and cuts its rows at its own time horizon (as ML-Agents'
trainers do), and a run resumes each behavior from its newest readable file. A behavior
the config does not name is said to train with the defaults."""

from __future__ import annotations

import logging

import pytest
import torch

from driver.training.checkpoints import Checkpoints
from learners.host import checkpoint
from learners.trainer_config.parse import ConfigError, parse_config

TWO = {
    "behaviors": {
        "Striker": {"checkpoint_interval": 100, "keep_checkpoints": 2, "time_horizon": 16},
        "Goalie": {"checkpoint_interval": 250, "keep_checkpoints": 3, "time_horizon": 40},
    }
}
NAMES = {"Striker": "Striker?team=0", "Goalie": "Goalie?team=1"}


def entry(steps: int) -> dict:
    return {"network": {"w": torch.full((2,), float(steps))}, "steps": steps, "updates": []}


def learner_state(steps: dict[str, int], version: int, only: list[str] | None = None) -> dict:
    """What the learner's ``state_dict(only)`` returns."""
    behaviors = {b: entry(n) for b, n in steps.items() if only is None or b in only}
    return {"step": sum(steps.values()), "version": version, "behaviors": behaviors}


def run(tmp_path, until: int, start: dict[str, int] | None = None) -> Checkpoints:
    """Both behaviors step 50 at a time (the Goalie half as fast); the driver saves the
    due ones after each step, as its loop does, and everything at the end."""
    saver = Checkpoints(tmp_path, parse_config(TWO), start or {})
    steps = dict.fromkeys(NAMES.values(), 0) | (start or {})
    for version in range(1, until // 50 + 1):
        steps[NAMES["Striker"]] += 50
        steps[NAMES["Goalie"]] += 25
        if due := saver.due(steps):
            saver.save(learner_state(steps, version, due), {"run_id": "two"})
    saver.save(learner_state(steps, until // 50), {"run_id": "two"})
    return saver


def saved_steps(tmp_path, folder: str) -> list[int]:
    return sorted(int(p.stem.split("-")[1]) for p in (tmp_path / "checkpoints" / folder).glob("*"))


def test_each_behavior_checkpoints_at_its_own_interval_and_keeps_its_own_count(tmp_path):
    run(tmp_path, 1000)
    # Striker: 100, 200 ... 1000 (10 saves), the newest 2 kept; Goalie: 250, 500 (+ 500 at
    # the end), the newest 3 kept
    assert saved_steps(tmp_path, "Striker_team0") == [900, 1000]
    assert saved_steps(tmp_path, "Goalie_team1") == [250, 500]
    state = checkpoint.load(tmp_path)
    assert {b: e["steps"] for b, e in state["behaviors"].items()} == {
        NAMES["Striker"]: 1000,
        NAMES["Goalie"]: 500,
    }
    assert state["step"] == 1500 and state["version"] == 20


def test_a_resumed_run_checkpoints_from_where_each_behavior_was(tmp_path):
    run(tmp_path, 1000)
    state = checkpoint.load(tmp_path)
    start = {b: int(e["steps"]) for b, e in state["behaviors"].items()}
    saver = Checkpoints(tmp_path, parse_config(TWO), start)
    assert saver.next_step == {NAMES["Striker"]: 1100, NAMES["Goalie"]: 750}


def test_a_corrupt_newest_checkpoint_is_named_and_the_one_before_used(tmp_path, caplog):
    run(tmp_path, 1000)
    newest = tmp_path / "checkpoints" / "Striker_team0" / "step-0000001000.pt"
    newest.write_bytes(newest.read_bytes()[:10])  # as a kill mid-write without the rename
    with caplog.at_level(logging.WARNING):
        state = checkpoint.load(tmp_path)
    assert state["behaviors"][NAMES["Striker"]]["steps"] == 900
    assert any(str(newest) in r.getMessage() for r in caplog.records)


def test_no_readable_checkpoint_of_a_behavior_is_a_one_line_error(tmp_path):
    run(tmp_path, 1000)
    for path in (tmp_path / "checkpoints" / "Goalie_team1").glob("*.pt"):
        path.write_bytes(b"garbage")
    with pytest.raises(checkpoint.CheckpointError, match="Goalie_team1: no readable") as error:
        checkpoint.load(tmp_path)
    assert "\n" not in str(error.value)


def test_the_service_cuts_each_behaviors_rows_at_its_own_time_horizon():
    from driver.options import TrainOptions
    from driver.system import service_config
    from rollout.collecting.horizons import Horizons
    from rollout.environment.unity import UnityConfig

    settings = service_config(TrainOptions(), parse_config(TWO), UnityConfig(None), False)
    assert settings.horizon == Horizons(64, {"Striker": 16, "Goalie": 40})
    assert settings.horizon(NAMES["Goalie"]) == 40 and settings.horizon("Other") == 64


def test_a_threaded_behavior_lets_workers_collect_one_buffer_through_its_updates():
    """ML-Agents' ``threaded``: its environments step on while the trainer updates. Here
    the service's collect-ahead: the largest buffer of a threaded on-policy behavior, or
    ``--collect-ahead`` if larger; off-policy trainers keep workers busy anyway."""
    from driver.options import TrainOptions
    from driver.system import service_config
    from rollout.environment.unity import UnityConfig

    def ahead(behaviors: dict, collect_ahead: int = 0, default: dict | None = None) -> int:
        raw = {"behaviors": behaviors} | ({"default_settings": default} if default else {})
        options = TrainOptions(collect_ahead=collect_ahead)
        return service_config(options, parse_config(raw), UnityConfig(None), False).collect_ahead

    ppo = {"threaded": True, "hyperparameters": {"buffer_size": 4096, "batch_size": 256}}
    poca = {"trainer_type": "poca", "threaded": True, "hyperparameters": {"buffer_size": 8000}}
    sac = {"trainer_type": "sac", "threaded": True}
    assert ahead({"A": ppo, "B": {}}) == 4096
    assert ahead({"A": ppo, "B": poca}) == 8000
    assert ahead({"A": ppo}, collect_ahead=10_000) == 10_000
    assert ahead({"A": sac, "B": {}}) == 0
    assert ahead({"A": {}}) == 0
    assert ahead({"A": {}}, default={"threaded": True}) == 10_240  # ML-Agents' buffer_size


def spec(*shapes: tuple[int, ...]) -> dict:
    observations = [{"name": f"sensor{i}", "shape": list(shape)} for i, shape in enumerate(shapes)]
    return {"observations": observations}


def test_a_behavior_the_config_does_not_name_is_reported_once(caplog):
    """As mlagents-learn: without a config file, a warning and the defaults."""
    from driver.training.behavior_notes import BehaviorNotes

    notes = BehaviorNotes(parse_config({}, "<defaults>"), no_graphics=False)
    with caplog.at_level(logging.WARNING):
        notes.report({"3DBallHard?team=0": spec((8,))})
        notes.report({"3DBallHard?team=0": spec((8,)), "3DBallHard?team=1": spec((8,))})
    said = [r.getMessage() for r in caplog.records]
    assert said == [
        "Behavior name 3DBallHard does not match any behaviors specified in the trainer "
        "configuration file. A default configuration will be used."
    ]


def test_a_config_file_must_name_every_behavior_or_give_default_settings(caplog):
    """As mlagents-learn: a file without default_settings that lacks the build's behavior
    stops the run, naming what to add; with default_settings, those serve (and we say so)."""
    from driver.options import TrainingError
    from driver.training.behavior_notes import BehaviorNotes

    named = BehaviorNotes(parse_config(TWO, "two.yaml"), no_graphics=False)
    named.report({NAMES["Striker"]: spec((8,))})  # named: nothing to say
    with pytest.raises(TrainingError, match=r"behavior 3DBall is not in two\.yaml: add it under"):
        named.report({"3DBall?team=0": spec((8,))})
    with_defaults = parse_config({**TWO, "default_settings": {"max_steps": 10}}, "two.yaml")
    with caplog.at_level(logging.WARNING):
        BehaviorNotes(with_defaults, no_graphics=False).report({"3DBall?team=0": spec((8,))})
    assert [r.getMessage() for r in caplog.records] == [
        "3DBall is not among the behaviors of two.yaml: it trains with default_settings"
    ]


def test_cameras_without_graphics_are_a_warning(caplog):
    from driver.training.behavior_notes import BehaviorNotes

    with caplog.at_level(logging.WARNING):
        BehaviorNotes(parse_config(TWO), no_graphics=False).report(
            {"Striker?team=0": spec((3, 84, 84))}
        )
        assert caplog.records == []
        BehaviorNotes(parse_config(TWO), no_graphics=True).report(
            {"Striker?team=0": spec((3, 84, 84), (8,)), "Goalie?team=1": spec((8,))}
        )
    (said,) = [r.getMessage() for r in caplog.records]
    assert said.startswith("Striker?team=0 observes images (sensor0) and the build runs without")


def test_even_checkpoints_spread_them_over_max_steps_as_mlagents() -> None:
    """ML-Agents' TrainerSettings: checkpoint_interval = max_steps / keep_checkpoints."""
    config = parse_config(
        {
            "default_settings": {"even_checkpoints": True, "max_steps": 1_000_000},
            "behaviors": {
                "A": {"keep_checkpoints": 4, "checkpoint_interval": 7},
                "B": {"even_checkpoints": False, "checkpoint_interval": 7},
            },
        }
    )
    assert config.for_behavior("A").checkpoint_interval == 250_000  # the interval given yields
    assert config.for_behavior("B").checkpoint_interval == 7
    assert config.default.checkpoint_interval == 200_000  # 5 kept by default
    assert config.unsupported == ()
    with pytest.raises(ConfigError, match=r"behaviors\.A\.even_checkpoints: expected true or"):
        parse_config({"behaviors": {"A": {"even_checkpoints": "yes"}}})
