"""unitysim against the real UnityEnvironment: seeding, side channels, areas, editor mode."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from mlagents_envs.base_env import ActionTuple
from mlagents_envs.environment import UnityEnvironment
from mlagents_envs.side_channel.engine_configuration_channel import EngineConfigurationChannel
from mlagents_envs.side_channel.environment_parameters_channel import (
    EnvironmentParametersChannel,
)

from tests.helpers import free_port

pytestmark = pytest.mark.integration
BALL = "3DBall?team=0"


def rollout_3dball(env, steps: int, action_seed: int = 0) -> list[np.ndarray]:
    """Observations of a fixed action sequence (decisions and terminals, in order)."""
    rng = np.random.default_rng(action_seed)
    env.reset()
    seen = []
    for _ in range(steps):
        decisions, terminals = env.get_steps(BALL)
        seen += [terminals.obs[0].copy(), decisions.obs[0].copy()]
        actions = rng.uniform(-1, 1, size=(len(decisions), 2)).astype(np.float32)
        env.set_actions(BALL, ActionTuple(continuous=actions))
        env.step()
    return seen


def test_same_seed_same_actions_same_observations(open_env):
    with open_env("3DBall", seed=5) as env:
        first = rollout_3dball(env, 40)
    with open_env("3DBall", seed=5) as env:
        second = rollout_3dball(env, 40)
    with open_env("3DBall", seed=6) as env:
        other = rollout_3dball(env, 40)
    assert all(np.array_equal(a, b) for a, b in zip(first, second, strict=True))
    assert not all(np.array_equal(a, b) for a, b in zip(first, other, strict=False))


def test_reset_restarts_episodes_without_terminal_infos(open_env):
    with open_env("3DBall", seed=1) as env:
        rollout_3dball(env, 10)
        env.reset()
        decisions, terminals = env.get_steps(BALL)
        assert len(terminals) == 0 and len(decisions) == 12
        assert np.allclose(decisions.obs[0][:, 3], 4.0)  # balls dropped from 4 units up


def first_fall(env, parameters: EnvironmentParametersChannel, **values: float) -> np.ndarray:
    for key, value in values.items():
        parameters.set_float_parameter(key, value)
    env.reset()
    env.step()  # zero actions: one decision period of free fall
    decisions, _ = env.get_steps(BALL)
    return decisions.obs[0]


def test_environment_parameters_change_the_dynamics(open_env):
    parameters = EnvironmentParametersChannel()
    with open_env("3DBall", seed=3, side_channels=[parameters]) as env:
        light = first_fall(env, parameters, gravity=4.0)
        heavy = first_fall(env, parameters, gravity=40.0)
    vy_light, vy_heavy = light[:, 6], heavy[:, 6]
    assert np.all((vy_heavy < vy_light) & (vy_light < 0)), (vy_light, vy_heavy)
    np.testing.assert_allclose(vy_heavy / vy_light, 10.0, rtol=1e-3)


def test_ball_scale_parameter_changes_resting_height(open_env):
    parameters = EnvironmentParametersChannel()
    with open_env("3DBall", seed=3, side_channels=[parameters]) as env:
        heights = {}
        for scale in (1.0, 3.0):
            parameters.set_float_parameter("scale", scale)
            env.reset()
            for _ in range(8):  # let the balls land
                env.step()
            decisions, _ = env.get_steps(BALL)
            heights[scale] = np.median(decisions.obs[0][:, 3])
    assert heights[3.0] > heights[1.0] + 0.4  # a bigger ball rests higher (radius 0.5 * scale)


def test_sampled_parameters_are_reproducible(open_env):
    def falls() -> np.ndarray:
        parameters = EnvironmentParametersChannel()
        parameters.set_uniform_sampler_parameters("gravity", 5.0, 30.0, seed=1234)
        with open_env("3DBall", seed=3, side_channels=[parameters]) as env:
            env.reset()
            env.step()
            return env.get_steps(BALL)[0].obs[0][:, 6]

    first, second = falls(), falls()
    np.testing.assert_array_equal(first, second)
    gravity = -first / 0.1  # one decision period of fall
    assert np.all((gravity > 4.9) & (gravity < 30.1))


def test_engine_configuration_is_applied_and_logged(open_env, tmp_path):
    engine = EngineConfigurationChannel()
    engine.set_configuration_parameters(width=84, height=84, time_scale=20.0)
    with open_env("3DBall", side_channels=[engine]) as env:
        env.reset()
        env.step()
    log = (tmp_path / "Player-0.log").read_text()
    assert "width=84, height=84" in log and "time_scale=20.0" in log
    assert "trainer closed the session (status 400)" in log or "connection to the trainer" in log


def test_num_areas_replicates_training_areas(open_env):
    with open_env("3DBall", num_areas=3) as env:
        env.reset()
        decisions, _ = env.get_steps(BALL)
        assert len(decisions) == 36
        assert sorted(decisions.agent_id) == list(range(36))


def test_steps_after_reset_keep_agent_order_and_actions(open_env):
    """Actions are applied to the i-th reported decision agent: full tilt on agent 0 only."""
    with open_env("3DBall", seed=2) as env:
        env.reset()
        for _ in range(3):
            decisions, _ = env.get_steps(BALL)
            actions = np.zeros((len(decisions), 2), dtype=np.float32)
            actions[decisions.agent_id_to_index[0]] = [1.0, 1.0]
            env.set_actions(BALL, ActionTuple(continuous=actions))
            env.step()
        decisions, _ = env.get_steps(BALL)
        rotation = decisions.obs[0][:, :2]
        start_rotation_bound = np.sin(np.radians(10.0) / 2)
        moved = np.abs(rotation) > start_rotation_bound + 0.05
        assert moved[decisions.agent_id_to_index[0]].all()
        assert not moved[decisions.agent_id != 0].any()


def test_editor_mode_connects_like_pressing_play():
    port = free_port()
    editor = subprocess.Popen(
        [sys.executable, "-m", "unitysim", "editor", "--env", "3DBall", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        env = UnityEnvironment(file_name=None, base_port=port, timeout_wait=30)
        try:
            env.reset()
            env.step()
            decisions, _ = env.get_steps(BALL)
            assert len(decisions) == 12
        finally:
            env.close()
        assert editor.wait(timeout=15) == 0
    finally:
        if editor.poll() is None:
            editor.kill()
            editor.wait()


def test_editor_mode_gives_up_without_a_trainer():
    """It gives up by itself (after 1 s): ``run`` raises at 120 s, a safety stop."""
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "unitysim",
            "editor",
            "--env",
            "Basic",
            "--port",
            str(free_port()),
            "--connect-timeout",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0
