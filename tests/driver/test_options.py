"""The run options are declared once (driver/options.py): the command line, its help, the
defaults and the checks all come from the declaration."""

from __future__ import annotations

import dataclasses

import pytest

from driver.cli import build_parser, main
from driver.options import (
    CollectOptions,
    TrainingError,
    TrainOptions,
    flag,
    from_arguments,
)


@pytest.mark.parametrize(
    ("command", "kind"), [("train", TrainOptions), ("collect", CollectOptions)]
)
def test_the_command_line_is_the_declaration(command, kind):
    """Every field is an option of its command, with the declared default, and nothing
    else is: no second list of options to keep in step."""
    arguments = build_parser().parse_args([command])
    assert from_arguments(kind, arguments) == kind()
    declared = {item.name for item in dataclasses.fields(kind)}
    parsed = set(vars(arguments)) - {"command", "func"}
    assert parsed == declared


def test_help_shows_each_option_with_its_help(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for item in dataclasses.fields(TrainOptions):
        name = "--no-progress" if item.name == "progress" else flag(item.name)
        assert name in text
        assert " ".join(item.metadata["option"].help.split()[:4]) in text


def test_values_reach_their_fields():
    argv = "train --workers auto --max-steps 500 --torch-device cpu --no-progress"
    argv += " --restarts-rate-limit-n 3 --max-workers 4"
    arguments = build_parser().parse_args(argv.split())
    options = from_arguments(TrainOptions, arguments)
    assert (options.workers, options.max_steps, options.device) == ("auto", 500, "cpu")
    assert options.progress is False and options.restarts.rate_limit_n == 3


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--max-steps", "-1"], "--max-steps: at least 1, got -1"),
        (["--num-areas", "0"], "--num-areas: at least 1, got 0"),
        (["--workers", "0"], "--workers: at least 1, got 0"),
        (["--max-seconds", "0"], "--max-seconds: positive, got 0"),
        (["--collect-ahead", "-5"], "--collect-ahead: at least 0, got -5"),
        (["--run-id", "../escape"], "--run-id: one directory name"),
        (["--run-id", "a/b"], "--run-id: one directory name"),
        (["--run-id", ".."], "--run-id: one directory name"),
        (["--restarts-rate-limit-period-s", "0"], "--restarts-rate-limit-period-s: positive"),
        (["--max-workers", "3"], "--max-workers: a number of at least 1, with --workers auto"),
        (["--env", "editor"], "--env editor: there is one editor"),
    ],
)
def test_bad_values_are_one_line_errors_before_ray_starts(argv, message, capsys, monkeypatch):
    def no_ray(*args, **kwargs):
        raise AssertionError("Ray was started")

    monkeypatch.setattr("driver.local_ray.BackgroundRay", no_ray)
    assert main(["train", *argv]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"error: {message}")
    assert len(captured.err.strip().splitlines()) == 1


def test_validation_is_the_same_for_callers_of_train():
    with pytest.raises(TrainingError, match="--cpus: at least 1, got 0"):
        TrainOptions(cpus=0).validate()
    with pytest.raises(TrainingError, match="--seconds: positive"):
        CollectOptions(seconds=-1).validate()


def test_the_training_docs_list_every_option():
    """docs/training.md's table is the one other place options are named: it may not lag."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs/training.md").read_text()
    missing = [
        name
        for item in dataclasses.fields(TrainOptions)
        if f"`{(name := item.metadata['option'].negative or flag(item.name))}`" not in text
    ]
    assert missing == []
