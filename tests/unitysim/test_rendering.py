"""A player started with -nographics renders nothing, as a Unity player: its cameras send
blank frames, and its grid sensors, computed rather than rendered, are as they were."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.integration


@pytest.mark.parametrize("no_graphics", [False, True], ids=["graphics", "nographics"])
def test_cameras_send_blank_frames_without_graphics(open_env, no_graphics):
    with open_env("GridWorld", no_graphics=no_graphics) as env:
        env.reset()
        decisions, _ = env.get_steps("GridWorld?team=0")
        camera, goal = decisions.obs  # CameraSensor, GoalSignal
        assert camera.ndim == 4  # agents, then the image
        assert (camera.max() == 0) == no_graphics
        assert goal.any()  # a vector observation, never rendered


def test_grid_sensors_are_computed_without_graphics(open_env):
    with open_env("GridFoodCollector", no_graphics=True) as env:
        env.reset()
        (grid,) = env.get_steps(next(iter(env.behavior_specs)))[0].obs
        assert grid.ndim == 4 and grid.any()
