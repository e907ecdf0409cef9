"""Only the configured reward signals are used, merged as mlagents-learn merges them: a
behavior's ``reward_signals`` replace the default (extrinsic) one, and add to those of
``default_settings`` when the file has that section."""

from __future__ import annotations

import pytest

from learners.trainer_config.parse import parse_config

GAIL = {"gail": {"strength": 1.0, "demo_path": "x.demo"}}


@pytest.mark.parametrize(
    ("data", "strength"),
    [
        ({"behaviors": {"B": {}}}, 1.0),  # no reward_signals: the extrinsic one
        ({"behaviors": {"B": {"reward_signals": {"extrinsic": {"strength": 0.5}}}}}, 0.5),
        ({"behaviors": {"B": {"reward_signals": GAIL}}}, 0.0),  # GAIL alone: no env reward
        ({"default_settings": {}, "behaviors": {"B": {"reward_signals": GAIL}}}, 1.0),
        (
            {
                "default_settings": {"reward_signals": GAIL},
                "behaviors": {"B": {"reward_signals": {"extrinsic": {"strength": 0.2}}}},
            },
            0.2,
        ),
        ({"default_settings": {"reward_signals": GAIL}, "behaviors": {"B": {}}}, 0.0),
    ],
    ids=["default", "extrinsic", "gail-only", "over-defaults", "added", "from-defaults"],
)
def test_the_extrinsic_reward_counts_only_when_configured(data, strength):
    config = parse_config(data)
    assert config.for_behavior("B").reward_strength == strength
    if "gail" in str(data):  # GAIL is merged in as the extrinsic signal is
        assert [s.kind for s in config.for_behavior("B").reward_signals] == ["gail"]
