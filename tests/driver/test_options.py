"""The run options are declared once (driver/options.py): the command line, its help, the
defaults and the checks all come from the declaration."""

from __future__ import annotations

import re

import pytest

from driver.cli import build_parser, main
from driver.declaration import TrainingError, declared, flag, from_arguments, from_settings
from driver.options import CollectOptions, TrainOptions
from learners.trainer_config.parse import parse_config


@pytest.mark.parametrize(
    ("command", "kind"), [("train", TrainOptions), ("collect", CollectOptions)]
)
def test_the_command_line_is_the_declaration(command, kind):
    """Every field is an option of its command, with the declared default, and nothing
    else is: no second list of options to keep in step."""
    arguments = build_parser().parse_args([command])
    assert from_arguments(kind, arguments) == kind()
    names = {item.name for item, _ in declared(kind)}
    parsed = set(vars(arguments)) - {"command", "func"}
    assert parsed == names


def test_help_shows_each_option_with_its_help(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    flags = set(re.findall(r"--[a-z-]+", text))
    for item, how in declared(TrainOptions):
        name = how.negative or flag(item.name)
        if how.hidden:  # mlagents-learn's deprecated and removed options, accepted
            assert name not in flags
            continue
        assert name in text
        assert " ".join(how.help.split()[:4]) in text


def test_values_reach_their_fields():
    argv = "train my.yaml --num-envs auto --max-steps 500 --torch-device cpu --no-progress"
    argv += " --restarts-rate-limit-n 3 --max-workers 4 --load --env-args --level 3 -x"
    options = from_arguments(TrainOptions, build_parser().parse_args(argv.split()))
    assert (options.workers, options.max_steps, options.device) == ("auto", 500, "cpu")
    assert options.progress is False and options.restarts.rate_limit_n == 3
    assert options.config == "my.yaml" and options.resume  # --load: mlagents-learn's old name
    assert options.env_args == ("--level", "3", "-x")
    assert options.given == {
        "config", "workers", "max_steps", "device", "progress", "restarts_rate_limit_n",
        "max_workers", "resume", "env_args",
    }  # fmt: skip


def test_the_config_is_given_once():
    with pytest.raises(TrainingError, match="--config: given twice, as trainer_config_path"):
        from_arguments(
            TrainOptions, build_parser().parse_args(["train", "a.yaml", "--config", "b.yaml"])
        )


RUN_LEVEL = {
    "env_settings": {"num_envs": 3, "seed": 7, "base_port": 6000, "env_args": ["-a", "1"]},
    "checkpoint_settings": {"run_id": "from-yaml", "force": True, "results_dir": "out"},
    "debug": True,
}


def test_a_trainer_configs_run_level_sections_give_way_to_the_command_line():
    """mlagents-learn's precedence: the command line, then the file, then the default."""
    options = from_arguments(TrainOptions, build_parser().parse_args(["train", "--seed", "1"]))
    merged = from_settings(options, RUN_LEVEL, "run.yaml")
    assert (merged.workers, merged.seed, merged.base_port) == (3, 1, 6000)
    assert merged.env_args == ("-a", "1") and merged.debug
    assert (merged.run_id, merged.force, merged.results_dir) == ("from-yaml", True, "out")


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"env_settings": {"num_env": 3}}, "env_settings.num_env: unknown key; did you mean"),
        ({"env_settings": {"num_envs": "many"}}, "env_settings.num_envs: expected int, got"),
        ({"checkpoint_settings": {"force": "yes"}}, "checkpoint_settings.force: expected true"),
        ({"env_settings": [1]}, "env_settings: expected a mapping"),
    ],
)
def test_a_bad_run_level_key_is_one_line(settings, message):
    with pytest.raises(TrainingError) as error:
        from_settings(TrainOptions(), settings, "run.yaml")
    assert str(error.value).startswith(f"run.yaml: {message}")


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
    names = [how.negative or flag(item.name) for item, how in declared(TrainOptions)]
    assert [name for name in names if f"`{name}`" not in text] == []


def test_mlagents_learns_engine_and_environment_options_reach_every_unity():
    """The command line's engine options over the config's engine_settings, arguments for
    the executable, the first instance alone with graphics, ports from --base-port."""
    from pathlib import Path

    from driver.options import TrainOptions
    from driver.system import service_config, unity_config
    from rollout.environment.ports import PortRange

    config = parse_config({"engine_settings": {"width": 64, "time_scale": 5, "no_graphics": True}})
    options = TrainOptions(
        time_scale=1.0, env_args=("-level", "3"), no_graphics_monitor=True, base_port=6000
    )
    unity = unity_config(options, config, Path("run"))
    assert (unity.engine.width, unity.engine.time_scale, unity.engine.height) == (64, 1.0, 84)
    assert unity.additional_args == ("-level", "3")
    assert unity.no_graphics and unity.no_graphics_monitor
    assert service_config(options, config, unity, False).port_range == PortRange(6000, 6099)


def test_the_learner_takes_every_core_only_where_the_workers_wait_through_its_updates(
    monkeypatch,
):
    """2 learner threads trained POCA's 512-wide SoccerTwos config 1.5 times as fast as one
    on 2 cores, where the workers wait through each update; where they collect beside it
    (SAC, IMPALA, collecting ahead, ``threaded``) they keep their cores."""
    from driver.system import learner_threads

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)

    def threads(trainers: list[str], **given: object) -> int:
        behaviors = {f"B{i}": {"trainer_type": t} for i, t in enumerate(trainers)}
        return learner_threads(TrainOptions(**given), parse_config({"behaviors": behaviors}))

    assert threads(["ppo"]) == threads(["poca", "ppo"]) == 0  # 0: every core of its node
    assert threads([]) == 0  # defaults: PPO
    assert threads(["sac"]) == threads(["ppo", "sac"]) == threads(["impala"]) == 1
    assert threads(["ppo"], collect_ahead=1000) == 1
    threaded = {"behaviors": {"B": {"trainer_type": "ppo", "threaded": True}}}
    assert learner_threads(TrainOptions(), parse_config(threaded)) == 1
    assert threads(["ppo"], learner_threads=3) == threads(["sac"], learner_threads=3) == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert threads(["ppo"]) == threads(["sac"]) == 2
    assert threads(["ppo"], learner_threads=1) == 1


def test_a_learner_given_zero_threads_takes_every_core_it_may_run_on():
    import os

    import torch

    from learners.host.devices import usable_cores
    from learners.host.learner import CentralLearner

    before = torch.get_num_threads()
    try:
        CentralLearner(parse_config({}), torch_threads=0)
        assert torch.get_num_threads() == usable_cores() <= len(os.sched_getaffinity(0))
        CentralLearner(parse_config({}), torch_threads=1)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
