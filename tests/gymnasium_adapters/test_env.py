"""The Gymnasium adapters over real unitysim players (real gRPC, no mocks): spaces from the
behavior specs, gymnasium's own checker, seeded determinism, SAME_STEP autoreset with
final observations and episode statistics checked against 3DBall's reward rule, masks,
one-line errors, and Stable-Baselines3 PPO learning Basic through ``UnityGymEnv``."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

from gymnasium_adapters import AgentSetError, UnityGymEnv, UnityVectorEnv
from rollout.environment.restarts import RestartPolicy
from rollout.environment.unity import UnityConfig, UnityError
from tests.helpers import leak_checked_allocator, wait_gone

pytestmark = pytest.mark.integration


@pytest.fixture
def allocator(tmp_path):
    with leak_checked_allocator(tmp_path, 24500, 24599) as allocator:
        yield allocator


def one_line(error: pytest.ExceptionInfo) -> str:
    message = str(error.value)
    assert "\n" not in message and message
    return message


def test_basic_spaces_masks_and_gymnasium_checker(allocator):
    with UnityGymEnv("unitysim:Basic", allocator=allocator) as env:
        assert env.behavior_name == "Basic?team=0"
        assert env.observation_space == spaces.Box(-np.inf, np.inf, (20,), np.float32)
        assert env.action_space == spaces.Discrete(3)
        obs, info = env.reset()
        assert obs.dtype == np.float32 and obs.argmax() == 10 and obs.sum() == 1
        assert info["action_mask"].dtype == np.bool_ and info["action_mask"].tolist() == [1, 1, 1]
        assert env.action_masks().shape == (3,)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # infinite Box bounds, no render modes
            check_env(env)
        # Walk right to the large goal: 7 moves of -0.01, +1 at the end, terminated.
        env.reset()
        rewards = []
        for _ in range(7):
            obs, reward, terminated, truncated, info = env.step(2)
            rewards.append(reward)
        assert terminated and not truncated
        assert obs.argmax() == 17  # the terminal observation, not the next episode's
        np.testing.assert_allclose(rewards, [-0.01] * 6 + [0.99], atol=1e-6)
        assert info["episode"]["l"] == 7 and info["episode"]["r"] == pytest.approx(0.93)
        with pytest.raises(UnityError, match="reset"):
            env.step(0)
        obs, info = env.reset()  # Unity reset the agent already: a new id, back at 10
        assert obs.argmax() == 10 and info["agent_id"] > 0


def test_wrong_actions_and_multi_agent_behaviors_give_one_line_errors(allocator):
    with UnityGymEnv(UnityConfig("unitysim:Basic"), allocator=allocator) as env:
        env.reset()
        with pytest.raises(ValueError) as error:
            env.step(np.array([0, 1]))
        assert "shape ()" in one_line(error) and "Discrete(3)" in str(error.value)
        with pytest.raises(ValueError) as error:
            env.step(3)
        assert "out of range" in one_line(error)
        obs, *_ = env.step(np.int64(1))  # still usable after the errors
        assert obs.argmax() == 9
    with pytest.raises(UnityError) as error:
        UnityGymEnv("unitysim:3DBall", allocator=allocator)
    assert "12 agents" in one_line(error) and "UnityVectorEnv" in str(error.value)
    with pytest.raises(UnityError) as error:
        UnityGymEnv("unitysim:WallJump", allocator=allocator)
    assert "SmallWallJump?team=0" in one_line(error) and "behavior=" in str(error.value)
    with pytest.raises(UnityError) as error:
        UnityVectorEnv("unitysim:Basic", behavior="Nope", allocator=allocator)
    assert "Basic?team=0" in one_line(error)


def test_close_leaves_no_process_and_is_idempotent(allocator):
    env = UnityGymEnv("unitysim:Basic", allocator=allocator)
    pid = env.unity.player_pid
    env.reset()
    env.close()
    env.close()
    assert wait_gone(pid)
    with pytest.raises(UnityError, match="closed"):
        env.step(0)
    vector = UnityVectorEnv("unitysim:3DBall", allocator=allocator)
    pid = vector.unity.player_pid
    vector.close()
    vector.close()
    assert vector.closed and wait_gone(pid)


def run_3dball(env: UnityVectorEnv, seed: int, steps: int) -> tuple[list, list]:
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    observations, rewards = [obs], []
    for _ in range(steps):
        obs, reward, *_ = env.step(env.action_space.sample())
        observations.append(obs)
        rewards.append(reward)
    return observations, rewards


def test_3dball_vector_env_spaces_autoreset_and_episode_statistics(allocator):
    env = UnityVectorEnv("unitysim:3DBall", seed=5, allocator=allocator)
    try:
        assert env.num_envs == 12
        assert env.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
        assert env.single_observation_space == spaces.Box(-np.inf, np.inf, (8,), np.float32)
        assert env.single_action_space == spaces.Box(-1.0, 1.0, (2,), np.float32)
        assert env.observation_space.shape == (12, 8) and env.action_space.shape == (12, 2)
        obs, info = env.reset()
        assert obs in env.observation_space and "action_mask" not in info
        with pytest.raises(ValueError) as error:
            env.step(np.zeros(2, np.float32))
        assert "(12, 2)" in one_line(error)
        env.action_space.seed(0)
        returns, lengths, episodes = np.zeros(12), np.zeros(12, np.int64), 0
        for _ in range(200):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert obs in env.observation_space and reward.dtype == np.float32
            assert not (terminated & truncated).any()
            returns += reward
            lengths += 1
            done = terminated | truncated
            assert np.array_equal(info.get("_episode", np.zeros(12, bool)), done)
            assert np.array_equal(info.get("_final_obs", np.zeros(12, bool)), done)
            for i in np.flatnonzero(done):
                # What the env reports equals what we summed, and 3DBall's rule: +0.1 per
                # decision while the ball is on, -1 on the step it falls (SetReward).
                assert info["episode"]["l"][i] == lengths[i]
                assert info["episode"]["r"][i] == pytest.approx(returns[i], abs=1e-5)
                assert terminated[i]  # no MaxStep within 200 decisions
                assert returns[i] == pytest.approx(0.1 * (lengths[i] - 1) - 1.0, abs=1e-4)
                final = info["final_obs"][i]
                assert final in env.single_observation_space
                assert not np.array_equal(final, obs[i])  # obs[i] begins the next episode
                returns[i], lengths[i], episodes = 0.0, 0, episodes + 1
        assert episodes >= 12  # random actions drop balls every few dozen decisions

        # Determinism: equal seeds and actions, equal trajectories; another seed differs.
        first = run_3dball(env, seed=9, steps=30)
        second = run_3dball(env, seed=9, steps=30)
        other = run_3dball(env, seed=10, steps=30)
        for a, b in zip(first[0], second[0], strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(np.array(first[1]), np.array(second[1]))
        assert not np.array_equal(first[0][0], other[0][0])
    finally:
        env.close()


def test_gridworld_images_masks_and_truncation(allocator):
    with UnityVectorEnv("unitysim:GridWorld", seed=1, allocator=allocator) as env:
        assert env.num_envs == 9
        single = env.single_observation_space
        assert isinstance(single, spaces.Dict) and list(single) == ["CameraSensor", "GoalSignal"]
        assert single["CameraSensor"] == spaces.Box(0.0, 1.0, (3, 40, 40), np.float32)
        assert single["GoalSignal"].shape == (2,)
        assert env.single_action_space == spaces.Discrete(5)
        obs, info = env.reset()
        assert obs in env.observation_space and obs["CameraSensor"].shape == (9, 3, 40, 40)
        assert info["action_mask"].shape == (9, 5) and info["action_mask"].dtype == np.bool_
        assert info["action_mask"][:, 0].all()  # staying is always allowed
        masked = 0
        rng = np.random.default_rng(0)
        for _ in range(20):  # random allowed moves
            mask = info["action_mask"]
            masked += int((~mask).sum())
            actions = np.array([rng.choice(np.flatnonzero(row)) for row in mask])
            obs, _, _, _, info = env.step(actions)
        assert masked > 0  # moves into walls are masked
        # Standing still never reaches a goal: MaxStep 100 interrupts -> truncated.
        env.reset()
        for _ in range(99):
            _, _, terminated, truncated, _ = env.step(np.zeros(9, np.int64))
            assert not (terminated | truncated).any()
        _, _, terminated, truncated, info = env.step(np.zeros(9, np.int64))
        assert truncated.all() and not terminated.any()
        assert info["episode"]["l"].tolist() == [100] * 9
        assert info["final_obs"][0]["CameraSensor"].shape == (3, 40, 40)


def test_vector_basic_reassigns_new_agent_ids_to_their_slots(allocator):
    with UnityVectorEnv("unitysim:Basic", num_areas=3, allocator=allocator) as env:
        assert env.num_envs == 3 and env.single_action_space == spaces.Discrete(3)
        obs, info = env.reset()
        first_ids = info["agent_id"].copy()
        actions = np.array([2, 1, 2])  # right, left, right: large, small, large goal
        for step in range(1, 8):
            obs, _, terminated, _, info = env.step(actions)
            assert terminated.tolist() == [step == 7, step in (3, 6), step == 7]
        np.testing.assert_allclose(info["episode"]["r"][[0, 2]], [0.93, 0.93], atol=1e-5)
        assert (info["agent_id"] != first_ids).all()  # every slot has a new agent id
        assert (obs.argmax(axis=1)[[0, 2]] == 10).all()  # SAME_STEP: the next episode


def test_agents_that_come_and_go_raise_where_it_happens(allocator):
    with UnityVectorEnv("unitysim:DungeonEscape", seed=0, allocator=allocator) as env:
        assert env.num_envs == 36
        env.reset()
        env.action_space.seed(0)
        with pytest.raises(AgentSetError) as error:
            for _ in range(300):
                env.step(env.action_space.sample())
        assert "agent set changed" in one_line(error)


def evaluate(env: gym.Env, policy, episodes: int, cap: int = 200) -> float:
    returns = []
    for _ in range(episodes):
        obs, _ = env.reset()
        total = 0.0
        for _ in range(cap):
            obs, reward, terminated, truncated, _ = env.step(policy(obs))
            total += reward
            if terminated or truncated:
                break
        returns.append(total)
    return float(np.mean(returns))


def test_stable_baselines3_ppo_learns_basic(allocator, tmp_path, monkeypatch):
    torch = pytest.importorskip("torch")
    monkeypatch.setenv("SB3_LOGDIR", str(tmp_path))  # else each learn() leaves a dir in /tmp
    ppo = pytest.importorskip("stable_baselines3").PPO
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with UnityGymEnv("unitysim:Basic", seed=0, allocator=allocator) as env:
            model = ppo("MlpPolicy", env, n_steps=256, batch_size=64, seed=0, device="cpu")
            model.learn(4096)
            trained = evaluate(env, lambda obs: model.predict(obs, deterministic=True)[0], 3)
            env.action_space.seed(0)
            random = evaluate(env, lambda obs: env.action_space.sample(), 30)
    finally:
        torch.set_num_threads(threads)
    # Random walks average about 0.05; going right to the large goal earns 0.93.
    assert trained > 0.5 and trained > random + 0.4, (trained, random)


def test_hybrid_actions_are_a_dict(allocator):
    with UnityVectorEnv("unitysim:GridFoodCollector", seed=2, allocator=allocator) as env:
        assert env.num_envs == 20
        assert env.single_action_space == spaces.Dict(
            continuous=spaces.Box(-1.0, 1.0, (3,), np.float32), discrete=spaces.Discrete(2)
        )
        assert env.single_observation_space == spaces.Box(0.0, 1.0, (5, 40, 40), np.float32)
        env.reset()
        env.action_space.seed(2)
        for _ in range(10):
            obs, *_, info = env.step(env.action_space.sample())
        assert obs in env.observation_space and info["action_mask"].shape == (20, 2)
        with pytest.raises(ValueError) as error:
            env.step(np.zeros((20, 3), np.float32))
        assert "'continuous' and 'discrete'" in one_line(error)


def test_a_crashed_player_restarts_and_the_episode_ends_truncated(allocator):
    config = UnityConfig(
        "unitysim:Basic",
        additional_args=("--sim-crash-after", "4"),
        restarts=RestartPolicy(backoff_s=0.01),
    )
    with UnityGymEnv(config, allocator=allocator) as env:
        first_pid = env.unity.player_pid
        env.reset()
        for _ in range(3):  # staying put: no goal, the crash ends the episode
            assert not env.step(0)[3]
        obs, reward, terminated, truncated, info = env.step(0)  # the 4th STEP: it crashes
        assert truncated
        assert not terminated and reward == 0.0 and info["unity_restarted"]
        assert obs.argmax() == 10  # the last observation before the crash
        assert env.unity.restarts == 1 and env.unity.player_pid != first_pid
        obs, _ = env.reset()
        assert obs.argmax() == 10
        obs, *_ = env.step(2)
        assert obs.argmax() == 11
