"""AnimalArena: spec over the real protocol, what the camera shows, rewards, episode ends,
parameters applied at the next episode, and a camera-driven policy that beats random play."""

from __future__ import annotations

import numpy as np
import pytest
from mlagents_envs.base_env import ActionTuple
from mlagents_envs.side_channel.environment_parameters_channel import (
    EnvironmentParametersChannel,
)

from tests.unitysim.test_learnable_envs import check_infos, make, random_actions, run
from unitysim.envs.animal_arena import FOOD, PALETTE, TOP_SPEED, AnimalArena
from unitysim.envs.base import Actions, AgentInfos, SimEnv
from unitysim.envs.perception import FLOOR, SKY, WALL_X, WALL_Y

NAME = "AnimalArena?team=0"
AGENTS = AnimalArena.fields_per_area
FOOD_RGB = PALETTE[FOOD][:, None, None]  # (3, 1, 1)


def act(env: SimEnv, moves: list[tuple[int, int]] | tuple[int, int]) -> AgentInfos:
    """One step with (move, turn) per agent (or the same for all)."""
    discrete = np.broadcast_to(np.asarray(moves, dtype=np.int32), (env.n, 2))
    return env.step({NAME: Actions(np.zeros((env.n, 0), np.float32), discrete.copy())})[NAME]


def food_columns(image: np.ndarray) -> np.ndarray:
    """Columns of one (3, H, W) image that show food somewhere."""
    return np.flatnonzero((image == FOOD_RGB).all(axis=0).any(axis=0))


def place(env: AnimalArena, row: int, pos: tuple[float, float], heading: float) -> None:
    env.pos[row] = pos
    env.heading[row] = heading
    env.vel[row] = 0.0


# --- over the real protocol ------------------------------------------------------------


@pytest.mark.integration
def test_spec_and_lossless_images_through_the_protocol(open_env):
    expected = make("AnimalArena", seed=4).reset()[NAME]
    with open_env("AnimalArena", seed=4) as env:
        env.reset()
        assert list(env.behavior_specs) == [NAME]
        spec = env.behavior_specs[NAME]
        camera, velocity = spec.observation_specs
        assert (camera.name, camera.shape) == ("CameraSensor", (3, 84, 84))
        assert (velocity.name, velocity.shape) == ("Velocity", (3,))
        assert spec.action_spec.discrete_branches == (3, 3)
        assert spec.action_spec.continuous_size == 0
        decisions, terminals = env.get_steps(NAME)
        assert len(decisions) == AGENTS and len(terminals) == 0
        np.testing.assert_array_equal(decisions.agent_id, np.arange(AGENTS))
        assert decisions.obs[0].dtype == np.float32 and decisions.obs[1].dtype == np.float32
        np.testing.assert_array_equal(decisions.obs[0], expected.obs[0])  # PNG is lossless
        np.testing.assert_array_equal(decisions.obs[1], 0.0)
        forward = np.tile(np.array([[1, 0]], dtype=np.int32), (AGENTS, 1))
        for _ in range(3):
            env.set_actions(NAME, ActionTuple(discrete=forward))
            env.step()
        decisions, _ = env.get_steps(NAME)
        velocity_obs = decisions.obs[1]
        assert (velocity_obs[:, 2] > 0.0).all() and (velocity_obs[:, 1] == 0.0).all()


@pytest.mark.integration
def test_episode_length_from_the_side_channel(open_env):
    parameters = EnvironmentParametersChannel()
    with open_env("AnimalArena", seed=1, side_channels=[parameters]) as env:
        parameters.set_float_parameter("episode_length", 3.0)
        parameters.set_float_parameter("food_count", 0.0)
        env.reset()
        for step in range(1, 4):
            env.step()
            decisions, terminals = env.get_steps(NAME)
            assert len(decisions) == AGENTS
            np.testing.assert_allclose(decisions.reward if step < 3 else terminals.reward, -1 / 3)
        assert len(terminals) == AGENTS and terminals.interrupted.all()


# --- the camera --------------------------------------------------------------------------


def test_camera_shows_food_ahead_and_not_behind() -> None:
    env = make("AnimalArena", seed=0, food_count=1, arena_size=40.0)
    env.reset()
    env.food[0, 0] = (5.0, 0.0)
    rows = np.array([0])
    place(env, 0, (0.0, 0.0), 0.0)
    ahead = food_columns(env.camera(rows)[0])
    assert {41, 42} <= set(ahead.tolist()) and ahead.min() > 20 and ahead.max() < 63
    place(env, 0, (0.0, 0.0), np.pi)
    assert len(food_columns(env.camera(rows)[0])) == 0
    place(env, 0, (0.0, 0.0), 0.5)  # turned left: the food is to the right
    assert food_columns(env.camera(rows)[0]).min() > 50
    place(env, 0, (-18.0, 0.0), 0.0)  # 23 away: small, but there
    far = food_columns(env.camera(rows)[0])
    assert 1 <= len(far) < len(ahead) and {41, 42} <= set(far.tolist())


def test_images_are_exact_bytes_and_show_sky_walls_floor() -> None:
    for out in run(make("AnimalArena", seed=2), 20):
        images = out[NAME].obs[0]
        np.testing.assert_array_equal(np.rint(images * 255) / np.float32(255), images)
    env = make("AnimalArena", seed=2, food_count=0)
    env.reset()
    place(env, 0, (0.0, 0.0), 1.0)
    image = env.camera(np.array([0]))[0]
    np.testing.assert_array_equal(image[:, 0], np.broadcast_to(PALETTE[SKY][:, None], (3, 84)))
    np.testing.assert_array_equal(image[:, -1], np.broadcast_to(PALETTE[FLOOR][:, None], (3, 84)))
    walls = (image[:, 41, :, None] == PALETTE[[WALL_X, WALL_Y]].T[:, None]).all(axis=0)
    assert walls.any(axis=1).all()  # just above the horizon: the walls all around
    assert walls.any(axis=0).all()  # both shades: a corner is in view


# --- rewards, episodes, dynamics ---------------------------------------------------------


def test_time_penalty_and_interruption_at_t() -> None:
    env = make("AnimalArena", seed=0, food_count=0, episode_length=7)
    env.reset()
    for _ in range(2):  # two episodes
        for _ in range(6):
            infos = act(env, (1, 1))
            assert not infos.done.any() and (infos.reward == np.float32(-1 / 7)).all()
        infos = act(env, (1, 1))
        assert infos.done.sum() == AGENTS and infos.max_step_reached[infos.done].all()
        assert (infos.reward[infos.done] == np.float32(-1 / 7)).all()
        assert (infos.reward[~infos.done] == 0.0).all()
        np.testing.assert_array_equal(infos.agent_id, np.tile(np.arange(AGENTS), 2))


def test_touching_food_gives_one_and_ends_the_episode() -> None:
    env = make("AnimalArena", seed=0, episode_length=100)
    env.reset()
    place(env, 0, (0.0, 0.0), 0.0)
    env.food[0, 0] = (4.0, 0.0)
    still = [(0, 0)] * env.n
    forward = [(1, 0), *still[1:]]
    for _ in range(20):
        infos = act(env, forward)
        if infos.done[0]:
            break
    assert infos.done[0] and not infos.max_step_reached[0]
    assert infos.reward[0] == np.float32(1.0 - 1 / 100)
    assert len(food_columns(infos.obs[0][0])) > 20  # the terminal image: food fills the view


def test_velocity_in_the_agent_frame_and_walls_stop() -> None:
    env = make("AnimalArena", seed=0, food_count=0, arena_size=20.0)
    env.reset()
    place(env, 0, (-5.0, 0.0), 0.0)
    for _ in range(8):
        infos = act(env, (1, 0))
    velocity = infos.obs[1][0]
    assert velocity[2] == pytest.approx(TOP_SPEED, rel=0.05) and velocity[1] == 0.0
    assert abs(velocity[0]) < 1e-4
    infos = act(env, (0, 1))  # coast while turning right: the motion now points left
    assert infos.obs[1][0, 0] < -0.5 and infos.obs[1][0, 2] > 0.0
    for _ in range(30):
        infos = act(env, (1, 0))
    assert env.pos[0, 0] == pytest.approx(9.5)  # against the wall, half 10 minus radius 0.5
    assert abs(env.pos[0, 1]) < 9.5 and infos.obs[1][0, 2] < 0.5 * TOP_SPEED


def wall_height_from_the_centre(env: AnimalArena) -> int:
    """Wall pixels in the middle column of agent 0's view from the arena's centre."""
    place(env, 0, (0.0, 0.0), 0.0)
    column = env.camera(np.array([0]))[0, :, :, 42]
    shades = PALETTE[[WALL_X, WALL_Y]][:, :, None]
    return int((column == shades).all(axis=1).any(axis=0).sum())


def test_parameters_apply_at_the_next_episode() -> None:
    env = make("AnimalArena", seed=3, food_count=0, episode_length=4)
    env.reset()
    env.params.values.update(arena_size=32.0, food_count=3.0, episode_length=9.0)
    assert (env.half == 6.0).all() and not env.present.any()  # not before the episode ends
    near = wall_height_from_the_centre(env)
    for _ in range(4):
        infos = act(env, (0, 1))
    assert infos.done.sum() == AGENTS  # the old T still held
    assert (env.half == 16.0).all() and (env.present.sum(axis=1) == 3).all()
    assert (np.abs(env.food[:, :3]) <= 16.0).all() and (np.abs(env.pos) <= 15.5).all()
    assert (np.abs(env.pos) > 6.0).any() and (np.abs(env.food) > 6.0).any()
    env.present[0] = False  # an unobstructed view of the walls
    assert 2 * wall_height_from_the_centre(env) <= near  # walls 16 away, not 6
    ends = [act(env, (0, 1)).done.any() for _ in range(9)]
    assert ends == [False] * 8 + [True]  # the new T


# --- learnability and the shared contract -------------------------------------------------


def camera_policy(images: np.ndarray) -> np.ndarray:
    """Turn until the food is near the centre, then go forward; search turning right."""
    green = (images == FOOD_RGB).all(axis=1).any(axis=1)  # (n, W)
    columns = np.arange(images.shape[-1])
    seen = green.any(axis=1)
    centre = (green * columns).sum(axis=1) / np.maximum(green.sum(axis=1), 1) - 41.5
    move = np.where(seen & (np.abs(centre) < 12), 1, 0)
    turn = np.where(~seen | (centre > 4), 1, np.where(centre < -4, 2, 0))
    return np.column_stack([move, turn]).astype(np.int32)


def collect(env: SimEnv, steps: int, policy: str) -> tuple[int, float]:
    """Food eaten and the mean return of finished episodes over ``steps`` decisions."""
    rng = np.random.default_rng(0)
    out = env.reset()
    eaten, returns, running = 0, [], np.zeros(env.n)
    for _ in range(steps):
        infos = out[NAME]
        np.add.at(running, infos.agent_id, infos.reward)
        for agent, interrupted in zip(
            infos.agent_id[infos.done], infos.max_step_reached[infos.done], strict=True
        ):
            eaten += not interrupted
            returns.append(running[agent])
            running[agent] = 0.0
        if policy == "camera":
            images = infos.obs[0][~infos.done]
            actions = {NAME: Actions(np.zeros((len(images), 0), np.float32), camera_policy(images))}
        else:
            actions = random_actions(env, out, rng)
        out = env.step(actions)
    return eaten, float(np.mean(returns))


def test_camera_policy_collects_far_more_than_random() -> None:
    eaten, mean_return = collect(make("AnimalArena", seed=0), 400, "camera")
    random_eaten, random_return = collect(make("AnimalArena", seed=0), 400, "random")
    assert eaten >= 40 and mean_return > 0.6
    assert eaten >= 5 * max(random_eaten, 1) and random_return < mean_return - 0.5


def test_contract_areas_and_determinism() -> None:
    env = make("AnimalArena", seed=5, num_areas=2)
    first = run(env, 60)
    assert len(first[0][NAME]) == 2 * AGENTS
    for out in first:
        check_infos(env, out)
    again = run(make("AnimalArena", seed=5, num_areas=2), 60)
    other = run(make("AnimalArena", seed=6, num_areas=2), 60)
    for a, b in zip(first, again, strict=True):
        for field in ("agent_id", "reward", "done", "max_step_reached"):
            np.testing.assert_array_equal(getattr(a[NAME], field), getattr(b[NAME], field))
        for x, y in zip(a[NAME].obs, b[NAME].obs, strict=True):
            np.testing.assert_array_equal(x, y)
    assert not np.array_equal(first[0][NAME].obs[0], other[0][NAME].obs[0])
