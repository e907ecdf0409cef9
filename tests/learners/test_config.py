"""Trainer-config YAML (no Ray): shipped configs load, ML-Agents' own files load, merge order
holds, and every bad value is one line naming its key."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import yaml

from batches.parameters import UNSEEDED, Constant, Uniform
from learners.trainer_config.parse import (
    CONFIG_DIR,
    ConfigError,
    config_for_env,
    defaults,
    load_config,
    parse_config,
)
from learners.trainer_config.settings import NetworkSettings, RunConfig

# ML-Agents' config/ppo/3DBall.yaml, as shipped with ML-Agents
MLAGENTS_PPO_3DBALL = """\
behaviors:
  3DBall:
    trainer_type: ppo
    hyperparameters:
      batch_size: 64
      buffer_size: 12000
      learning_rate: 0.0003
      beta: 0.001
      epsilon: 0.2
      lambd: 0.99
      num_epoch: 3
      learning_rate_schedule: linear
    network_settings:
      normalize: true
      hidden_units: 128
      num_layers: 2
      vis_encode_type: simple
    reward_signals:
      extrinsic:
        gamma: 0.99
        strength: 1.0
    keep_checkpoints: 5
    max_steps: 500000
    time_horizon: 1000
    summary_freq: 12000
"""

# ML-Agents' config/sac/3DBall.yaml: save_replay_buffer false is what we do anyway
MLAGENTS_SAC_3DBALL = """\
behaviors:
  3DBall:
    trainer_type: sac
    hyperparameters:
      learning_rate: 0.0003
      learning_rate_schedule: constant
      batch_size: 64
      buffer_size: 200000
      buffer_init_steps: 0
      tau: 0.005
      steps_per_update: 10.0
      save_replay_buffer: false
      init_entcoef: 0.5
      reward_signal_steps_per_update: 10.0
    network_settings:
      normalize: true
      hidden_units: 64
      num_layers: 2
      vis_encode_type: simple
    reward_signals:
      extrinsic:
        gamma: 0.99
        strength: 1.0
    keep_checkpoints: 5
    max_steps: 100000
    time_horizon: 1000
    summary_freq: 12000
    threaded: true
"""

UNITYSIM_BEHAVIORS = {
    "AnimalArena": {"AnimalArena"},
    "3DBall": {"3DBall"},
    "3DBallHard": {"3DBallHard"},
    "Basic": {"Basic"},
    "GridWorld": {"GridWorld"},
    "StrikersVsGoalie": {"Striker", "Goalie"},
    "SoccerTwos": {"SoccerTwos"},
    "Walker": {"Walker"},
    "Hallway": {"Hallway"},
    "Pyramids": {"Pyramids"},
    "DungeonEscape": {"DungeonEscape"},
    "GridFoodCollector": {"GridFoodCollector"},
    "WallJump": {"SmallWallJump", "BigWallJump"},
}


def parse(text: str) -> RunConfig:
    return parse_config(yaml.safe_load(text))


def one_behavior(section: str) -> dict:
    """A minimal config whose 3DBall behavior is the YAML ``section``."""
    return {"behaviors": {"3DBall": yaml.safe_load(section)}}


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_configs_load_cleanly(path: Path) -> None:
    config = load_config(path)
    assert config.behaviors
    assert config.unsupported == ()  # shipped configs ask only for what we implement
    assert path.read_text().startswith("#")
    env = path.stem.split("_")[0]
    assert set(config.behaviors) == UNITYSIM_BEHAVIORS[env]


def test_every_unitysim_env_has_a_config() -> None:
    for env in UNITYSIM_BEHAVIORS:
        assert config_for_env(env) == CONFIG_DIR / f"{env}.yaml"
    assert config_for_env("3DBall") == CONFIG_DIR / "3DBall.yaml"
    assert config_for_env("Echo") is None
    assert config_for_env("../pyproject") is None
    assert load_config(CONFIG_DIR / "3DBall_sac.yaml").for_behavior("3DBall").trainer_type == "sac"
    impala = load_config(CONFIG_DIR / "3DBall_impala.yaml").for_behavior("3DBall")
    assert impala.trainer_type == "impala"
    assert impala.hyperparameters.num_epoch == 1


def test_shipped_3dball_values() -> None:
    ball = load_config(config_for_env("3DBall")).for_behavior("3DBall?team=0")
    h = ball.hyperparameters
    assert (h.batch_size, h.buffer_size, h.learning_rate, h.num_epoch) == (256, 2400, 1e-3, 3)
    assert (h.beta, h.epsilon, h.lambd, h.max_policy_lag) == (1e-3, 0.2, 0.95, None)
    assert ball.network_settings == NetworkSettings(hidden_units=64, num_layers=2, normalize=True)
    assert (ball.gamma, ball.time_horizon, ball.max_steps) == (0.99, 64, 300_000)
    assert (ball.summary_freq, ball.checkpoint_interval) == (6000, 50_000)


def test_mlagents_ppo_3dball() -> None:
    config = parse(MLAGENTS_PPO_3DBALL)
    ball = config.for_behavior("3DBall?team=0")
    h = ball.hyperparameters
    assert ball.trainer_type == "ppo"
    assert (h.batch_size, h.buffer_size, h.learning_rate) == (64, 12000, 3e-4)
    assert (h.beta, h.epsilon, h.lambd, h.num_epoch) == (1e-3, 0.2, 0.99, 3)
    assert h.learning_rate_schedule == "linear"
    assert ball.network_settings == NetworkSettings(hidden_units=128, num_layers=2, normalize=True)
    assert (ball.gamma, ball.reward_strength) == (0.99, 1.0)
    assert (ball.keep_checkpoints, ball.max_steps, ball.time_horizon) == (5, 500_000, 1000)
    assert ball.summary_freq == 12000
    assert ball.checkpoint_interval == 500_000  # ML-Agents default
    assert config.unsupported == ()  # vis_encode_type: simple is what we do


def test_mlagents_sac_3dball() -> None:
    config = parse(MLAGENTS_SAC_3DBALL)
    ball = config.for_behavior("3DBall")
    h = ball.hyperparameters
    assert (ball.trainer_type, h.batch_size, h.buffer_size) == ("sac", 64, 200_000)
    assert (h.tau, h.steps_per_update, h.init_entcoef) == (0.005, 10.0, 0.5)
    assert h.learning_rate_schedule == "constant"
    assert h.reward_signal_steps_per_update == 10.0  # no reward signal network to update
    assert ball.threaded  # workers collect through its updates (driver/system.py)
    assert config.unsupported == ()


def test_defaults_follow_mlagents() -> None:
    ppo, sac = defaults("ppo"), defaults("sac")
    assert defaults() == ppo
    assert (sac.hyperparameters.batch_size, sac.hyperparameters.buffer_size) == (128, 50_000)
    assert sac.hyperparameters.learning_rate_schedule == "constant"
    assert (ppo.hyperparameters.batch_size, ppo.hyperparameters.buffer_size) == (1024, 10240)
    assert (ppo.hyperparameters.beta, ppo.max_steps, ppo.summary_freq) == (5e-3, 500_000, 50_000)
    assert ppo.network_settings == NetworkSettings()
    empty = parse_config({})
    assert empty.default == ppo
    assert empty.for_behavior("Anything?team=1") == ppo


def test_merge_order_and_team_suffix() -> None:
    config = parse(
        """
default_settings:
  hyperparameters: {batch_size: 100, learning_rate: 1.0e-3}
  network_settings: {hidden_units: 32}
  max_steps: 1000
behaviors:
  3DBall:
    hyperparameters: {batch_size: 50}
    reward_signals: {extrinsic: {gamma: 0.9}}
  Basic: ~
  Walker:
    trainer_type: sac
    hyperparameters: {tau: 0.01}
"""
    )
    ball = config.for_behavior("3DBall?team=0")
    assert ball.hyperparameters.batch_size == 50  # behavior over default_settings
    assert ball.hyperparameters.learning_rate == 1e-3  # default_settings, same section
    assert ball.hyperparameters.num_epoch == 3  # built-in default
    assert ball.network_settings == NetworkSettings(hidden_units=32)
    assert (ball.gamma, ball.reward_strength, ball.max_steps) == (0.9, 1.0, 1000)
    assert config.for_behavior("Basic").hyperparameters.batch_size == 100
    assert config.default.hyperparameters.batch_size == 100
    assert config.for_behavior("Unknown?team=1") is config.default
    walker = config.for_behavior("Walker")  # SAC defaults under default_settings
    assert walker.hyperparameters.buffer_size == 50_000
    assert walker.hyperparameters.batch_size == 100
    assert walker.hyperparameters.tau == 0.01
    assert walker.network_settings.hidden_units == 32


def test_numbers_as_yaml_leaves_them() -> None:
    config = parse_config(
        one_behavior("{hyperparameters: {learning_rate: 3.0e-4}, max_steps: 5.0e5}")
    )
    ball = config.for_behavior("3DBall")
    assert ball.hyperparameters.learning_rate == pytest.approx(3e-4)
    assert ball.max_steps == 500_000 and isinstance(ball.max_steps, int)
    assert parse_config(one_behavior("{reward_signals: {extrinsic: {gamma: 1}}}")).behaviors[
        "3DBall"
    ].gamma == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("section", "start", "detail"),
    [
        (
            "{hyperparameters: {learning_rate: fast}}",
            "behaviors.3DBall.hyperparameters.learning_rate:",
            "expected a positive number, got 'fast'",
        ),
        (
            "{hyperparameters: {batch_size: -64}}",
            "behaviors.3DBall.hyperparameters.batch_size:",
            "positive integer",
        ),
        (
            "{hyperparameters: {batch_size: 12.5}}",
            "behaviors.3DBall.hyperparameters.batch_size:",
            "positive integer",
        ),
        (
            "{hyperparameters: {learning_rate_schedule: cosine}}",
            "behaviors.3DBall.hyperparameters.learning_rate_schedule:",
            "linear, constant",
        ),
        (
            "{hyperparameter: {batch_size: 64}}",
            "behaviors.3DBall.hyperparameter:",
            "did you mean 'hyperparameters'?",
        ),
        (
            "{hyperparameters: {batchsize: 64}}",
            "behaviors.3DBall.hyperparameters.batchsize:",
            "did you mean 'batch_size'?",
        ),
        ("{max_steps: true}", "behaviors.3DBall.max_steps:", "got True"),
        ("{network_settings: {normalize: 1}}", "behaviors.3DBall.network_settings.normalize:", ""),
        (
            "{hyperparameters: {batch_size: 4096, buffer_size: 2048}}",
            "behaviors.3DBall.hyperparameters.batch_size:",
            "buffer_size",
        ),
        (
            "{reward_signals: {extrinsic: {gamma: 1.5}}}",
            "behaviors.3DBall.reward_signals.extrinsic.gamma:",
            "(0, 1]",
        ),
        ("{hyperparameters: {lambd: -0.1}}", "behaviors.3DBall.hyperparameters.lambd:", "[0, 1]"),
        ("{hyperparameters: {epsilon: 0}}", "behaviors.3DBall.hyperparameters.epsilon:", ""),
        ("{trainer_type: dqn}", "behaviors.3DBall.trainer_type:", "ppo, sac, poca, impala"),
        ("{hyperparameters: {tau: 0.01}}", "behaviors.3DBall.hyperparameters.tau:", "not a ppo"),
        ("{hyperparameters: [1, 2]}", "behaviors.3DBall.hyperparameters:", "mapping"),
        ("{reward_signals: {extrinsc: {}}}", "behaviors.3DBall.reward_signals.extrinsc:", "'extr"),
        ("{max_steps: .nan}", "behaviors.3DBall.max_steps:", ""),
        (
            "{network_settings: {vis_encode_type: cnn}}",
            "behaviors.3DBall.network_settings.vis_encode_type:",
            "expected one of simple, nature_cnn, resnet, match3, fully_connected, got 'cnn'",
        ),
    ],
)
def test_bad_values_name_their_key(section: str, start: str, detail: str) -> None:
    with pytest.raises(ConfigError) as caught:
        parse_config(one_behavior(section))
    message = str(caught.value)
    assert message.startswith(start), message
    assert detail in message
    assert "\n" not in message


def test_run_level_errors() -> None:
    with pytest.raises(ConfigError, match=r"^behavior: unknown key; did you mean 'behaviors'\?"):
        parse_config({"behavior": {}})
    with pytest.raises(ConfigError, match=r"^engine_settings.time_scale: expected a positive"):
        parse_config({"engine_settings": {"time_scale": "fast"}})
    with pytest.raises(ConfigError, match=r"^environment_parameters.mass: expected a number"):
        parse_config({"environment_parameters": {"mass": "heavy"}})
    with pytest.raises(ConfigError, match=r"^<config>: top level must be a mapping"):
        parse_config(["behaviors"])


def test_ml_agents_poca_configs_train_with_poca() -> None:
    config = load_config(Path(__file__).parents[1] / "mlagents_configs/poca/DungeonEscape.yaml")
    assert config.behaviors["DungeonEscape"].trainer_type == "poca"
    assert config.unsupported == ()


def test_unsupported_keys_are_reported(caplog: pytest.LogCaptureFixture) -> None:
    text = """
default_settings:
  reward_signals:
    extrinsic: {gamma: 0.99, network_settings: {hidden_units: 8}}
behaviors:
  Pyramids:
    init_path: results/old
    network_settings:
      vis_encode_type: resnet
      memory: {sequence_length: 64, memory_size: 128}
    hyperparameters: {beta_schedule: constant, shared_critic: false}
    reward_signals:
      extrinsic: {gamma: 0.99, strength: 1.0}
      curiosity: {gamma: 0.99, strength: 0.02}
      rnd: {gamma: 0.99, strength: 0.01}
    self_play: {window: 10}
    behavioral_cloning: {demo_path: x.demo}
  Hallway:
    network_settings: {vis_encode_type: simple, memory: null}
engine_settings: {time_scale: 20, width: 84, no_graphics: true}
environment_parameters:
  mass: 1.5
  scale: 1
  gravity: {sampler_type: uniform, sampler_parameters: {min_value: 7, max_value: 12}}
  wall: {curriculum: [{name: Lesson0, value: 1}]}
env_settings: {num_envs: 4}
checkpoint_settings: {run_id: x}
torch_settings: {device: cpu}
"""
    with caplog.at_level(logging.WARNING, logger="learners.trainer_config.parse"):
        config = parse(text)
    extrinsic_network = "default_settings.reward_signals.extrinsic.network_settings"
    assert set(config.unsupported) == {extrinsic_network}
    assert config.behaviors["Pyramids"].network_settings.memory is not None
    assert len(config.unsupported) == len(set(config.unsupported))
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert extrinsic_network in warnings[0].getMessage()
    values = {k: v[0].value for k, v in config.environment_parameters.items()}  # one lesson
    assert values == {"mass": Constant(1.5), "scale": Constant(1.0), "wall": Constant(1.0)} | {
        "gravity": Uniform(7.0, 12.0, UNSEEDED)  # the driver seeds it from the run's seed
    }
    assert dict(config.engine) == {"time_scale": 20.0, "width": 84, "no_graphics": True}
    assert config.for_behavior("Pyramids").gamma == 0.99
    assert config.for_behavior("Pyramids").init_path == "results/old"  # driver/training/planner.py
    cloning = config.for_behavior("Pyramids").behavioral_cloning
    assert cloning is not None and cloning.demo_path == str(Path("x.demo").resolve())
    assert config.for_behavior("Pyramids").network_settings.vis_encode_type == "resnet"
    assert config.run_settings["env_settings"] == {"num_envs": 4}  # the driver's options


@pytest.mark.parametrize("kind", ["simple", "nature_cnn", "resnet", "match3", "fully_connected"])
def test_every_visual_encoder_type_loads(kind: str) -> None:
    config = parse_config(
        {
            "default_settings": {"network_settings": {"vis_encode_type": kind}},
            "behaviors": {"GridWorld": {"network_settings": {"hidden_units": 64}}},
        }
    )
    assert config.unsupported == ()
    settings = config.for_behavior("GridWorld?team=0").network_settings
    assert settings == NetworkSettings(hidden_units=64, vis_encode_type=kind)
    assert defaults().network_settings.vis_encode_type == "simple"


def test_load_config_file_errors(tmp_path: Path) -> None:
    missing = tmp_path / "missing.yaml"
    with pytest.raises(ConfigError, match=rf"^{missing}: cannot read"):
        load_config(missing)
    broken = tmp_path / "broken.yaml"
    broken.write_text("behaviors:\n  3DBall: {trainer_type: ppo\n")
    with pytest.raises(ConfigError) as caught:
        load_config(broken)
    assert str(caught.value).startswith(f"{broken}: invalid YAML: line ")
    assert "\n" not in str(caught.value)
    scalar = tmp_path / "scalar.yaml"
    scalar.write_text("just text\n")
    with pytest.raises(ConfigError, match=rf"^{scalar}: top level must be a mapping"):
        load_config(scalar)
    good = tmp_path / "good.yaml"
    good.write_text(MLAGENTS_PPO_3DBALL)
    assert load_config(str(good)).source == str(good)


def test_max_policy_lag_is_off_unless_given_a_number() -> None:
    def lag(*value: object) -> int | None:
        section = {"hyperparameters": {"max_policy_lag": value[0]}} if value else {}
        return (
            parse_config({"behaviors": {"A": section}})
            .behaviors["A"]
            .hyperparameters.max_policy_lag
        )

    assert (lag(), lag(None), lag(0), lag(3)) == (None, None, 0, 3)
    with pytest.raises(ConfigError, match=r"max_policy_lag: expected an integer >= 0"):
        lag(-1)
