"""3DBall: its C physics against the numpy twin (in-process and through the player), and
MaxStep."""

from __future__ import annotations

import functools
import math
import shutil
import sys
import sysconfig
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from tests.unitysim.test_protocol import rollout_3dball
from unitysim.envs import ball3d
from unitysim.envs.ball3d import Ball3D
from unitysim.envs.base import Actions, AgentInfos, Parameters

BALL = "3DBall?team=0"
Policy = Callable[[np.ndarray, np.random.Generator], np.ndarray]

kernel = ball3d.compiled_physics()
needs_kernel = pytest.mark.skipif(kernel is None, reason="unitysim.envs._ball3d is not built")


@functools.cache
def libm_agrees_with_numpy() -> bool:
    """Both paths take sin and cos from libm where numpy does not use its own SIMD
    versions; only then must their trajectories agree to the last bit."""
    probe = np.random.default_rng(0).uniform(-0.6, 0.6, 4096)
    return np.array_equal(np.sin(probe), [math.sin(v) for v in probe]) and np.array_equal(
        np.cos(probe), [math.cos(v) for v in probe]
    )


def make(compiled: bool, seed: int = 0, num_areas: int = 1, **params: float) -> Ball3D:
    env = Ball3D(np.random.default_rng(seed), num_areas, Parameters(dict(params)))
    if not compiled:
        env.kernel = None
    return env


def random_policy(obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Beyond the action range, with some NaN (no turn) too."""
    actions = rng.uniform(-1.5, 1.5, (len(obs), 2)).astype(np.float32)
    actions[rng.random(actions.shape) < 0.02] = np.nan
    return actions


def balancing_policy(obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tilt each platform toward the slope that brings its ball back to the centre.
    Observations: rotation z, x (quaternion components: half the signed tilt), position
    x, y, z, velocity x, y, z."""
    del rng
    gain, to_centre, damping = 5.0, 0.05, 0.4
    about_z = gain * (-2 * obs[:, 0] + to_centre * obs[:, 2] + damping * obs[:, 5])
    about_x = gain * (-2 * obs[:, 1] - to_centre * obs[:, 4] - damping * obs[:, 7])
    return np.stack([about_z, about_x], axis=1).astype(np.float32)


class Played(list[AgentInfos]):
    """The messages of a run, and the float64 state after each (observations are float32,
    so they would hide a difference in the last bits)."""

    states: list[np.ndarray]


def play(env: Ball3D, decisions: int, policy: Policy, seed: int = 1) -> Played:
    rng = np.random.default_rng(seed)
    out = Played([env.reset()[BALL]])
    out.states = [env.state.copy()]
    for _ in range(decisions):
        rows = ~out[-1].done
        actions = policy(out[-1].obs[0][rows], rng)
        out.append(env.step({BALL: Actions(actions, np.zeros((len(actions), 0), np.int32))})[BALL])
        out.states.append(env.state.copy())
    return out


def assert_same(first: Played, second: Played, exact: bool) -> None:
    assert len(first) == len(second)
    if exact:
        np.testing.assert_array_equal(np.stack(first.states), np.stack(second.states))
    for a, b in zip(first, second, strict=True):
        for field in ("agent_id", "done", "max_step_reached"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        if exact:
            np.testing.assert_array_equal(a.obs[0], b.obs[0])
            np.testing.assert_array_equal(a.reward, b.reward)
        else:
            np.testing.assert_allclose(a.obs[0], b.obs[0], rtol=0, atol=1e-5)
            np.testing.assert_allclose(a.reward, b.reward, rtol=0, atol=1e-6)


def test_the_compiled_physics_is_built_where_a_c_compiler_is(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """setup.py's extension is optional, so a broken build would fail silently."""
    headers = Path(sysconfig.get_paths()["include"], "Python.h")
    if not shutil.which("cc") or not headers.exists():
        pytest.skip("no C compiler (cc) or no Python headers here: the numpy physics runs")
    monkeypatch.delenv("UNITYSIM_PHYSICS", raising=False)
    assert ball3d.compiled_physics() is not None, (
        "unitysim.envs._ball3d did not build: delete .venv/.installed, run "
        "scripts/setup-venv.sh and read setup.py's build output"
    )


def test_the_switch_turns_the_compiled_physics_off(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("UNITYSIM_PHYSICS", "numpy")
    assert ball3d.compiled_physics() is None
    assert Ball3D(np.random.default_rng(0), 1, Parameters()).kernel is None


@needs_kernel
@pytest.mark.parametrize(
    ("num_areas", "params"),
    [(1, {}), (2, {"gravity": 20.0, "mass": 3.0, "scale": 1.5}), (1, {"mass": 0.2})],
)
def test_compiled_and_numpy_physics_give_the_same_random_play(
    num_areas: int, params: dict[str, float]
) -> None:
    """Falls, restarts, actions beyond the range and NaN actions, several parameters."""
    exact = libm_agrees_with_numpy()
    decisions = 600 if exact else 20  # apart by an ulp, chaotic trajectories part later
    first = play(make(True, 3, num_areas, **params), decisions, random_policy)
    second = play(make(False, 3, num_areas, **params), decisions, random_policy)
    assert_same(first, second, exact)
    falls = sum(int((o.done & ~o.max_step_reached).sum()) for o in first)
    assert falls > (10 * num_areas if exact else 0)  # the terminal path was taken


@pytest.mark.parametrize("compiled", [True, False] if kernel else [False])
def test_a_balanced_ball_stays_on_until_max_step(compiled: bool) -> None:
    """MaxStep 5000 at a decision every 5 steps: 1000 decisions of +0.1, then every agent
    is interrupted (done, max_step_reached) in the same message as its next decision."""
    out = play(make(compiled), ball3d.MAX_STEP // ball3d.DECISION_PERIOD, balancing_policy)
    for infos in out[:-1]:
        assert not infos.done.any()
    last = out[-1]
    terminal = last.done
    assert terminal.sum() == 12 and last.max_step_reached[terminal].all()
    assert len(last) == 24  # the terminal rows and the first decisions of new episodes
    np.testing.assert_array_equal(last.agent_id[terminal], last.agent_id[~terminal])
    returns = sum(infos.reward[:12] for infos in out[1:])
    np.testing.assert_allclose(returns, 100.0, atol=1e-3)


@needs_kernel
def test_compiled_and_numpy_physics_agree_at_max_step() -> None:
    exact = libm_agrees_with_numpy()
    decisions = ball3d.MAX_STEP // ball3d.DECISION_PERIOD
    assert_same(
        play(make(True, 5), decisions, balancing_policy),
        play(make(False, 5), decisions, balancing_policy),
        exact,
    )


@needs_kernel
def test_the_kernel_names_a_wrong_buffer() -> None:
    env = make(True)
    args = [env.state, env.turn, env.reach, env.reward, env.fell, 0.5, 0.2, 0.1, 0.02]
    constants = [ball3d.DT, ball3d.MAX_SIGMA, ball3d.HALF_WIDTH, ball3d.RESTING_TOLERANCE]
    assert kernel.physics_step(*args, *constants) == 0  # the balls start 4 units up
    for index, bad, name in [
        (0, env.state.astype(np.float32), "state"),
        (0, env.state.T.copy(), "state"),  # (n, 8): the right size, the wrong layout
        (0, env.state[:, ::2], "state"),
        (1, env.turn[:, :6], "turn"),
        (1, env.turn.T.copy(), "turn"),
        (2, env.reach[:-1], "reach"),
        (3, env.reward.astype(np.float64), "reward"),
        (4, env.fell.astype(np.int8), "fell"),
    ]:
        wrong = list(args)
        wrong[index] = bad
        with pytest.raises(ValueError, match=name):
            kernel.physics_step(*wrong, *constants)
    with pytest.raises(TypeError, match="13 arguments"):
        kernel.physics_step(*args)
    with pytest.raises(ValueError, match="obs"):
        kernel.observe(env.state, np.empty((12, 8), dtype=np.float64))
    with pytest.raises(ValueError, match="obs"):
        kernel.observe(env.state, np.empty((8, 12), dtype=np.float32))
    with pytest.raises(ValueError, match="actions"):
        kernel.act(np.zeros((12, 3), np.float32), env.turn, *ball3d.TURN_PER_AXIS)
    with pytest.raises(ValueError, match="turn"):
        kernel.act(np.zeros((11, 2), np.float32), env.turn, *ball3d.TURN_PER_AXIS)
    with pytest.raises(TypeError):
        kernel.act(np.zeros((12, 2), np.float32), env.turn, "fast", 1.0)


@pytest.mark.parametrize("compiled", [True, False] if kernel else [False])
def test_a_fall_on_the_max_step_is_a_fall_not_an_interruption(compiled: bool) -> None:
    """The step where every episode reaches MaxStep is also the step where one ball falls:
    that agent ends with -1 and without max_step_reached; the others are interrupted."""
    env = make(compiled)
    env.reset()
    env.academy_steps = 2 * ball3d.MAX_STEP - 1  # every episode began at MAX_STEP - 1 ...
    env.start[:] = ball3d.MAX_STEP - 1
    env.next_interrupt = env.academy_steps  # ... so the next physics step is the last
    env.xz[0, 0], env.vel[0, 0] = 2.99, 5.0  # and agent 0's ball leaves the platform in it
    no_turn = Actions(np.zeros((12, 2), np.float32), np.zeros((12, 0), np.int32))
    out = env.step({BALL: no_turn})[BALL]
    assert len(out) == 24 and out.done[:12].all() and not out.done[12:].any()
    assert out.agent_id[0] == 0 and not out.max_step_reached[0] and out.reward[0] == -1.0
    assert out.max_step_reached[1:12].all()
    np.testing.assert_array_equal(out.reward[1:12], np.float32(0.1))


@needs_kernel
def test_the_compiled_act_reads_strided_actions() -> None:
    """Actions may arrive as a view (the protobuf reader's rows)."""
    wide = np.random.default_rng(0).uniform(-2, 2, (12, 4)).astype(np.float32)
    wide[3, 2] = np.nan
    compiled, reference = make(True), make(False)
    compiled._act(wide[:, 1:3])
    reference._act(np.ascontiguousarray(wide[:, 1:3]))
    np.testing.assert_array_equal(compiled.turn, reference.turn)
    assert compiled.turn[1, 3] == 0.0 and np.abs(compiled.turn).max() == ball3d.TURN


@needs_kernel
@pytest.mark.integration
def test_the_player_takes_the_switch_and_plays_the_same(open_env, monkeypatch, tmp_path):
    """UNITYSIM_PHYSICS=numpy reaches a player started by UnityEnvironment; the same seed
    and actions give the same observations with either physics."""
    with open_env("3DBall", seed=5) as env:
        compiled = rollout_3dball(env, 60)
    assert "3DBall physics: C" in (tmp_path / "Player-0.log").read_text()
    monkeypatch.setenv("UNITYSIM_PHYSICS", "numpy")
    with open_env("3DBall", seed=5) as env:
        numpy = rollout_3dball(env, 60)
    assert "3DBall physics: numpy" in (tmp_path / "Player-0.log").read_text()
    assert len(compiled) == len(numpy)
    for a, b in zip(compiled, numpy, strict=True):
        if libm_agrees_with_numpy():
            np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)


@needs_kernel
def test_the_kernel_releases_every_buffer_it_takes() -> None:
    """Each call takes views of its arrays; a view not given back would keep the array
    alive forever (a leak in a player that runs for hours)."""
    env = make(True)
    arrays = [env.state, env.turn, env.reach, env.reward, env.fell]
    actions, obs = np.zeros((12, 2), np.float32), np.empty((12, 8), np.float32)
    before = [sys.getrefcount(a) for a in [*arrays, actions, obs]]
    constants = [0.5, 0.2, 0.1, 0.02, ball3d.DT, 0.5, 2.5, 1e-6]
    for _ in range(100):
        kernel.act(actions, env.turn, *ball3d.TURN_PER_AXIS)
        kernel.physics_step(*arrays, *constants)
        kernel.observe(env.state, obs)
        with pytest.raises(ValueError):  # a failure after some views were taken
            kernel.physics_step(*arrays[:4], env.fell.astype(np.int8), *constants)
        with pytest.raises(ValueError):
            kernel.observe(env.state, obs.astype(np.float64))
        with pytest.raises(ValueError):
            kernel.act(actions, env.turn.T.copy(), *ball3d.TURN_PER_AXIS)
    assert [sys.getrefcount(a) for a in [*arrays, actions, obs]] == before


def test_3dballhard_stacks_nine_velocity_free_frames_as_its_stacking_sensor():
    """3DBallHard observes rotation z, x and the ball's relative position (5 values, no
    velocity) over the last 9 decisions, oldest first, zeros after an episode begins; a
    terminal row shows its final frame; the physics are 3DBall's."""
    env = ball3d.Ball3DHard(np.random.default_rng(0), 1, Parameters())
    (behavior,) = env.behaviors
    assert behavior.name == "3DBallHard?team=0"
    assert [(s.name, s.shape) for s in behavior.sensors] == [
        ("StackingSensor_size9_VectorSensor_size5", (45,))
    ]
    first = env.reset()[behavior.name].obs[0]
    assert first.shape == (12, 45) and not first[:, :40].any()  # only the first frame
    plain = Ball3D(np.random.default_rng(0), 1, Parameters())
    full = plain.reset()["3DBall?team=0"].obs[0]
    np.testing.assert_array_equal(first[:, 40:], full[:, :5])  # the same, without velocity
    frames = [first]
    for _ in range(20):
        tilt = Actions(np.full((12, 2), 0.3, np.float32), np.zeros((12, 0), np.int32))
        out = env.step({behavior.name: tilt})
        infos = out[behavior.name]
        decided = infos.obs[0][~infos.done]
        if len(decided) == 12:
            frames.append(decided)
    second, third = frames[1], frames[2]
    np.testing.assert_array_equal(second[:, 35:40], first[:, 40:])  # shifted by one frame
    np.testing.assert_array_equal(third[:, 30:40], second[:, 35:45])
