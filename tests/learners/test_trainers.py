"""One registry of trainer types (learners/trainer_config/trainer_types.py): a new trainer is one
entry there and its algorithm module, and the config, the acting policy, the learner and the driver
all take it from that entry."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from learners.acting.factory import policy_factory
from learners.host.learner import make_algorithm
from learners.trainer_config.keys import POSITIVE, SHARED
from learners.trainer_config.parse import ConfigError, parse_config
from learners.trainer_config.settings import Hyperparameters
from learners.trainer_config.trainer_types import TRAINERS, TrainerType


@dataclass
class Recorder:
    """An algorithm that only records how it was made."""

    network: object
    settings: object
    compute: object


@pytest.fixture
def registered(monkeypatch):
    entry = TrainerType(
        "recorder",
        f"{__name__}:Recorder",
        {**SHARED, "tau": POSITIVE},
        {"save_replay_buffer": False},
        Hyperparameters(batch_size=7),
        squashed=True,
    )
    monkeypatch.setitem(TRAINERS, "recorder", entry)
    return entry


def test_a_new_trainer_is_one_entry(registered):
    config = parse_config(
        {"behaviors": {"Ball": {"trainer_type": "recorder", "hyperparameters": {"tau": 0.5}}}}
    )
    settings = config.for_behavior("Ball")
    assert settings.hyperparameters.batch_size == 7 and settings.hyperparameters.tau == 0.5
    assert policy_factory(config).settings_for("Ball?team=0").tanh_squash  # its network
    algorithm = make_algorithm(network="net", settings=settings)  # type: ignore[arg-type]
    assert isinstance(algorithm, Recorder) and algorithm.settings is settings
    with pytest.raises(ConfigError, match="num_epoch: not a recorder hyperparameter"):
        parse_config(
            {"behaviors": {"B": {"trainer_type": "recorder", "hyperparameters": {"num_epoch": 3}}}}
        )


def test_unknown_trainer_types_list_the_registry():
    with pytest.raises(ConfigError, match="expected one of ppo, sac, poca, impala, got 'dqn'"):
        parse_config({"behaviors": {"B": {"trainer_type": "dqn"}}})


def test_mlagents_defaults_are_not_reported():
    """Values that ask for what we do anyway: unthreaded updates, SAC's reward-signal
    updates (only networks of intrinsic signals have them)."""
    config = parse_config(
        {
            "behaviors": {
                "B": {
                    "trainer_type": "sac",
                    "threaded": False,
                    "hyperparameters": {"reward_signal_steps_per_update": 10.0},
                }
            }
        }
    )
    assert config.unsupported == ()
