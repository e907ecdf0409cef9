"""The FoodCollector stand-ins through the real client: GridFoodCollector's five-channel
grid decoded from its PNGs; VisualFoodCollector's spec, what its first-person camera shows
and the frozen flag beside it."""

from __future__ import annotations

import numpy as np
from mlagents_envs.base_env import ActionTuple

from tests.unitysim.test_learnable_envs import make
from unitysim.envs.base import Actions
from unitysim.envs.food_collector import (
    FOOD_CODE,
    PALETTE_CHANNELS,
    POISON_CODE,
    VisualFoodCollector,
)

NAME = "VisualFoodCollector?team=0"


def test_the_real_client_decodes_the_grid_of_five_channels_from_two_pngs(open_env):
    with open_env("GridFoodCollector", no_graphics=True) as env:
        env.reset()
        (spec,) = env.behavior_specs["GridFoodCollector?team=0"].observation_specs
        assert (spec.name, spec.shape) == ("GridSensor-OneHot", (5, 40, 40))
        decisions, _ = env.get_steps("GridFoodCollector?team=0")
        grid = decisions.obs[0]
        assert grid.shape == (20, 5, 40, 40)
        assert set(np.unique(grid).tolist()) == {0.0, 1.0}  # exact: one-hot survives PNG
        assert (grid.sum(1) <= 1).all()
        assert grid[:, 0].any() and grid[:, 2].any() and grid[:, 3].any()  # food, wall, poison


def test_the_real_client_sees_the_prefabs_camera_and_frozen_flag(open_env):
    with open_env("VisualFoodCollector") as env:  # rendered: a build with graphics
        env.reset()
        spec = env.behavior_specs[NAME]
        assert [(o.name, o.shape) for o in spec.observation_specs] == [
            ("CameraSensor", (3, 84, 84)),
            ("VectorSensor_size1", (1,)),
        ]
        assert spec.action_spec.continuous_size == 3
        assert spec.action_spec.discrete_branches == (2,)
        decisions, _ = env.get_steps(NAME)
        assert len(decisions) == 8
        camera, frozen = decisions.obs
        colours = {tuple(c) for c in np.round(PALETTE_CHANNELS.T * 255).astype(int)}
        rgb = np.round(camera * 255).astype(int).transpose(0, 2, 3, 1).reshape(-1, 3)
        seen = {tuple(c) for c in rgb}
        assert seen <= colours  # the PNGs decoded exactly, every pixel a palette colour
        assert not frozen.any()
        env.set_actions(NAME, ActionTuple(np.zeros((8, 3), np.float32), np.zeros((8, 1), np.int32)))
        env.step()


def pixels_of(image: np.ndarray, code: int) -> np.ndarray:
    """(H, W) bool: where one (3, H, W) image shows ``code``'s colour."""
    return (image == PALETTE_CHANNELS[:, code, None, None]).all(axis=0)


def test_the_camera_shows_food_ahead_and_poison_in_its_own_colour_and_nothing_behind():
    env = make("VisualFoodCollector")
    assert isinstance(env, VisualFoodCollector)
    env.reset()
    env.pos[:4] = [(0.0, 0.0), (-15.0, -15.0), (-15.0, 15.0), (15.0, -15.0)]
    env.heading[0] = 0.0  # facing +x
    env.food[0] = 1.0e4
    env.food[0, 0] = (5.0, 0.0)  # food straight ahead
    env.food[0, -1] = (-5.0, 0.0)  # poison straight behind
    image = env._observe(0, np.array([0]))[0][0]
    food = pixels_of(image, FOOD_CODE)
    assert food[:, 40:44].any() and not food[:, :30].any() and not food[:, 54:].any()
    assert not pixels_of(image, POISON_CODE).any()
    env.heading[0] = np.pi  # now the poison is ahead and the food behind
    image = env._observe(0, np.array([0]))[0][0]
    assert pixels_of(image, POISON_CODE)[:, 40:44].any()
    assert not pixels_of(image, FOOD_CODE).any()


def test_a_lasered_agent_is_frozen_and_says_so_in_its_vector():
    env = make("VisualFoodCollector")
    env.reset()
    env.pos[:4] = [(0.0, 0.0), (5.0, 0.0), (-15.0, 15.0), (15.0, -15.0)]
    env.heading[0] = 0.0  # agent 0 aims at agent 1, 5 ahead
    fire = np.zeros((8, 1), np.int32)
    fire[0] = 1
    out = env.step({NAME: Actions(np.zeros((8, 3), np.float32), fire)})
    frozen = out[NAME].obs[1][:, 0]
    assert frozen[1] == 1.0 and frozen.sum() == 1.0
