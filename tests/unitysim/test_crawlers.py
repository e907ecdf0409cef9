"""Crawler's and Worm's stand-ins: the examples' specs through the real client, what their
sensors report, and their rewards."""

from __future__ import annotations

import numpy as np
from mlagents_envs.base_env import ActionTuple

from tests.unitysim.test_learnable_envs import make
from unitysim.envs.base import Actions
from unitysim.envs.crawlers import CRAWLER_SPEED, MAX_STEP, TOUCH, WORM_SPEED, Crawler, Worm

CRAWLER, WORM = "Crawler?team=0", "Worm?team=0"


def test_the_real_client_sees_the_crawlers_physics_body_sensor_and_the_worms_vector(open_env):
    crawler = [("PhysicsBodySensor:Body", (126,)), ("VectorSensor_size32", (32,))]
    for name, behavior, sensors, actions in (
        ("Crawler", CRAWLER, crawler, 20),
        ("Worm", WORM, [("VectorSensor_size64", (64,))], 9),
    ):
        with open_env(name, no_graphics=True) as env:
            env.reset()
            spec = env.behavior_specs[behavior]
            assert [(o.name, o.shape) for o in spec.observation_specs] == sensors
            assert spec.action_spec.continuous_size == actions
            assert spec.action_spec.discrete_branches == ()
            decisions, _ = env.get_steps(behavior)
            assert sorted(decisions.agent_id.tolist()) == list(range(10))
            assert not np.asarray(decisions.group_id).any()
            env.set_actions(behavior, ActionTuple(continuous=np.zeros((10, actions), np.float32)))
            env.step()
            decisions, terminal = env.get_steps(behavior)
            assert len(decisions) == 10 and len(terminal) == 0


def act(env: Crawler | Worm, continuous: np.ndarray) -> dict:
    (behavior,) = env.behaviors
    return env.step({behavior.name: Actions(continuous.astype(np.float32), np.zeros((10, 0)))})


def test_the_crawlers_vector_reports_the_speed_to_match_its_velocity_and_the_target():
    env = make("Crawler", seed=3)
    env.reset()
    strengths = np.linspace(-1.0, 1.0, 8)
    actions = np.concatenate([np.full((10, 12), 0.5), np.tile(strengths, (10, 1))], axis=1)
    for _ in range(3):
        output = act(env, actions)
    vector = output[CRAWLER].obs[1]
    speed = vector[:, 6]
    assert ((speed >= 0.1) & (speed <= CRAWLER_SPEED)).all() and np.ptp(speed) > 1.0
    np.testing.assert_allclose(speed, env.speed, rtol=1e-6)
    velocity, goal = vector[:, 1:4], vector[:, 4:7]
    np.testing.assert_allclose(vector[:, 0], np.linalg.norm(goal - velocity, axis=1), rtol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(velocity, axis=1), np.abs(env.body.velocity), 1e-4)
    np.testing.assert_allclose(vector[:, 13], np.abs(env.body.target - env.body.pos), rtol=1e-5)
    assert (np.abs(vector[:, 7:11]).sum(axis=1) > 0).all()  # a rotation quaternion
    np.testing.assert_allclose(np.linalg.norm(vector[:, 7:11], axis=1), 1.0, rtol=1e-5)
    # per leg part: ground contact, then the strength its action set, from [-1, 1] to [0, 1]
    parts = vector[:, 16:].reshape(10, 4, 2, 2)  # legs, upper / lower, contact / strength
    assert set(np.unique(parts[..., 0]).tolist()) <= {0.0, 1.0}
    by_part = np.stack([strengths[:4], strengths[4:]], axis=1)  # uppers 12-15, lowers 16-19
    np.testing.assert_allclose(parts[..., 1], np.broadcast_to((by_part + 1) / 2, (10, 4, 2)))
    # the physics sensor: 9 bodies' position (3) and rotation (4), velocities, local rotations
    physics = output[CRAWLER].obs[0]
    poses = physics[:, :63].reshape(10, 9, 7)
    assert (poses[:, 0, :3] == 0).all()  # the body is where the orientation cube is
    np.testing.assert_allclose(np.linalg.norm(poses[..., 3:], axis=2), 1.0, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(physics[:, 90:].reshape(10, 9, 4), axis=2), 1.0, 1e-5)
    np.testing.assert_allclose(
        np.linalg.norm(physics[:, 63:66], axis=1), np.abs(env.body.velocity), rtol=1e-4
    )


def test_a_touched_target_pays_one_and_moves_and_max_step_interrupts():
    for env in (make("Crawler"), make("Worm")):
        (behavior,) = env.behaviors
        env.reset()
        before = env.body.target.copy()
        env.body.target[4] = env.body.pos[4] + 0.5 * TOUCH
        output = act(env, np.zeros((10, behavior.continuous)))
        reward = output[behavior.name].reward
        assert reward[4] >= 1.0 and (np.delete(reward, 4) < 1.0).all(), reward
        assert abs(env.body.target[4] - env.body.pos[4]) > TOUCH
        assert (np.delete(env.body.target, 4) == np.delete(before, 4)).all()
        env.episode_steps[:] = MAX_STEP - 2
        infos = act(env, np.zeros((10, behavior.continuous)))[behavior.name]
        assert infos.done[:10].all() and infos.max_step_reached[:10].all()
        assert (env.episode_steps < 5).all()  # the next episodes began


def test_the_worm_is_paid_for_its_heads_speed_only_within_30_degrees_of_the_target():
    env = make("Worm")
    env.reset()
    body = env.body
    distance, direction = body.to_target()
    off = np.radians([0.0, 10.0, 20.0, 29.0, 31.0, 45.0, 90.0, 135.0, 180.0, -25.0])
    body.heading[:] = np.angle(direction) + off
    body.velocity[:] = WORM_SPEED * direction  # the goal velocity
    env.joints.q[:] = 0.0
    reward = env._facing(direction)
    expected = np.where(np.abs(off) < np.radians(30.0), 1.0 - np.abs(off) / np.pi, 0.0)
    np.testing.assert_allclose(reward, expected, atol=1e-9)
    # the head's observations: the goal velocity ahead, its angle from the cube / 180
    vector = env._observe(0, np.arange(10))[0]
    np.testing.assert_allclose(vector[:, 1:4], np.tile([0.0, 0.0, WORM_SPEED], (10, 1)))
    np.testing.assert_allclose(vector[:, 4], np.abs(off) / np.pi, atol=1e-6)
    np.testing.assert_allclose(vector[:, 11], distance, rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(vector[:, 13:16], axis=1), WORM_SPEED, rtol=1e-6)


def test_the_worms_segments_trail_the_head_bent_by_their_joints():
    env = make("Worm")
    env.reset()
    env.joints.q[:] = 0.0
    straight = env._observe(0, np.arange(10))[0]
    # segment s's position relative to the head: 12 + 8 + 15 * (s - 1) + 7
    at = [12 + 8 + 15 * (s - 1) + 7 for s in (1, 2, 3)]
    distances = [np.linalg.norm(straight[:, i : i + 3], axis=1) for i in at]
    np.testing.assert_allclose(distances, [np.full(10, 0.6 * s) for s in (1, 2, 3)], rtol=1e-6)
    env.joints.q[:, :, 1] = 0.5  # every joint turns the next segment the same way
    bent = env._observe(0, np.arange(10))[0]
    assert (np.linalg.norm(bent[:, at[2] : at[2] + 3], axis=1) < 1.8 - 1e-3).all()
