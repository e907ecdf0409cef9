"""The rules of the spec-faithful environments, driven by placing things (white-box).

Why a module of its own: these tests put balls, agents and keys where a rule must fire and
read the environments' state, where ``test_spec_envs.py`` only plays them from outside.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.unitysim.test_spec_envs import make
from unitysim.envs import load
from unitysim.envs.base import Actions, Output, Parameters, SimEnv
from unitysim.envs.walljump import SMALL


def idle(env: SimEnv, output: Output) -> dict[str, Actions]:
    """Actions that do nothing: zeros (every branch's "none")."""
    return {b.name: Actions.empty(b, int((~output[b.name].done).sum())) for b in env.behaviors}


def step_until_done(env: SimEnv, output: Output, limit: int = 10) -> Output:
    for _ in range(limit):
        output = env.step(idle(env, output))
        if any(infos.done.any() for infos in output.values()):
            return output
    pytest.fail("no terminal info")


def rows_of(output: Output, ids: list[int], done: bool) -> dict[int, tuple[float, float, bool]]:
    """agent id -> (reward, group reward, interrupted) of its done (or decision) rows."""
    found = {}
    for infos in output.values():
        for i in np.flatnonzero(infos.done == done):
            if infos.agent_id[i] in ids:
                found[int(infos.agent_id[i])] = (
                    float(infos.reward[i]),
                    float(infos.group_reward[i]),
                    bool(infos.max_step_reached[i]),
                )
    return found


@pytest.mark.parametrize(
    ("name", "scorers", "conceders"),
    [("SoccerTwos", [1, 3], [0, 2]), ("StrikersVsGoalie", [0, 2], [1])],
)
def test_a_goal_ends_the_pitch_with_group_rewards(name, scorers, conceders):
    env = make(name)
    output = env.reset()
    x = env.half[0] - 0.5
    env.ball[0], env.ball_vel[0] = (x, 0.0), (10.0, 0.0)  # into the goal at +x
    rows = rows_of(step_until_done(env, output), scorers + conceders, done=True)
    assert sorted(rows) == sorted(scorers + conceders)  # the whole pitch, nobody else
    for agent in scorers:
        assert rows[agent][1] == pytest.approx(1.0, abs=0.01) and not rows[agent][2]
    for agent in conceders:
        assert rows[agent][1] == -1.0 and not rows[agent][2]


def test_strikers_own_end_is_a_wall():
    env = make("StrikersVsGoalie")
    output = env.reset()
    env.ball[0], env.ball_vel[0] = (-7.5, 0.0), (-10.0, 0.0)
    for _ in range(5):
        output = env.step(idle(env, output))
        assert not any(infos.done.any() for infos in output.values())
    assert env.ball_vel[0, 0] > 0  # bounced


def test_soccer_twos_is_laid_out_as_the_real_pitch():
    """As ``SoccerEnvController.ResetScene``: each team in its own half, 3.2 to 13.2 from
    the centre line, facing the other goal within 10 degrees; the ball near the centre."""
    env = make("SoccerTwos", num_areas=4)  # 32 pitches
    env.reset()
    blue = env.team == 0  # attacks +x, starts at -x
    x = np.where(blue, -env.pos[:, 0], env.pos[:, 0])
    assert (x >= 3.19 - 1e-9).all() and (x <= 13.19 + 1e-9).all() and np.ptp(x) > 8
    assert np.allclose(np.abs(env.pos[:, 1]), 1.2)
    facing = np.where(blue, 0.0, np.pi) - env.heading
    assert (np.abs(np.angle(np.exp(1j * facing))) <= np.radians(10.0) + 1e-9).all()
    assert (np.abs(env.ball) <= 2.5).all() and env.half == (15.5, 7.5)


def test_soccer_twos_agents_run_as_rigid_bodies_and_kick_when_going_forward():
    """A velocity change of 2 a physics step against drag 3: 30 a second after 0.8 s of
    running; a lateral action replaces the forward one at 0.3 of it. A forward
    agent meeting the ball kicks it off at its own speed's bounce plus 13.3."""
    env = make("SoccerTwos")
    output = env.reset()
    env.pos[:4] = [(-14.5, -5.0), (-10.0, 0.0), (-14.5, 5.0), (14.0, 3.0)]
    env.heading[:4] = 0.0
    env.ball[:] = (100.0, 100.0)  # out of the way
    run = idle(env, output)
    purple = "SoccerTwos?team=1"  # agents 0 and 2; blue: 1 and 3
    run[purple].discrete[:] = (1, 0, 0)  # forward
    run[purple].discrete[1] = (1, 1, 0)  # forward, and right: only right counts
    for _ in range(8):  # 40 physics steps
        output = env.step(run)
    assert env.velocity[0, 0] == pytest.approx(2.0 / 0.06 * (1 - 1.06**-40), rel=1e-6)
    assert env.velocity[0, 1] == 0.0
    assert env.velocity[2, 0] == pytest.approx(0.0, abs=1e-9)  # only across, at 0.3
    assert -env.velocity[2, 1] == pytest.approx(0.3 * env.velocity[0, 0], rel=1e-6)
    assert env.velocity[1].tolist() == [0.0, 0.0]  # idle
    env.ball[0], env.ball_vel[0] = env.pos[0] + (1.5, 0.0), (0.0, 0.0)
    output = env.step(run)
    # 1.8 x 50 / 53 of the closing speed, plus the kick, less the ball's drag since
    assert 55.0 < env.ball_vel[0, 0] < 1.7 * 30.1 + 13.4 and env.ball_vel[0, 1] == 0.0
    assert env.velocity[0, 0] < 30.0  # the ball took a little of the agent's momentum
    env.ball[0], env.ball_vel[0] = env.pos[1] + (0.5, 0.0), (0.0, 0.0)  # touching, idle
    env.step(run)
    assert np.abs(env.ball_vel[0]).max() == pytest.approx(0.0, abs=1e-9)  # no kick at rest


def test_soccer_twos_rays_are_sphere_casts():
    """A ray of radius 0.5 finds the ball (radius 0.62) 10 away between two rays 12
    degrees apart, where a thin ray would miss it."""
    env = make("SoccerTwos")
    output = env.reset()
    env.pos[:4] = [(0.0, 0.0), (-14.0, -7.0), (-14.0, 7.0), (-14.0, 0.0)]
    env.heading[0] = 0.0
    angle = np.radians(6.0)
    env.ball[0], env.ball_vel[0] = 10.0 * np.array([np.cos(angle), np.sin(angle)]), 0.0
    output = env.step(idle(env, output))
    infos = output["SoccerTwos?team=1"]
    row = int(np.flatnonzero((infos.agent_id == 0) & ~infos.done)[0])
    frame = infos.obs[0][row].reshape(3, 11, 8)[-1]  # the newest frame: 11 rays, 6 tags + 2
    seen = np.flatnonzero(frame[:, 0] == 1.0)  # rays whose tag is the ball
    assert len(seen) == 2  # the centre ray and the first to its left, neither straight at it
    assert (frame[seen, 7] * 20.0 < 10.0).all()


@pytest.mark.parametrize(("right", "reward"), [(True, 1.0), (False, -0.1)])
def test_hallway_rewards_the_goal_matching_the_symbol(right, reward):
    env = make("Hallway")
    output = env.reset()
    up_is_right = env.orange_up[0] != env.red[0]  # the +y goal has the symbol's colour
    env.pos[0] = (22.0, 7.0 if up_is_right == right else -7.0)  # on the goal pad
    (got, _, interrupted) = rows_of(step_until_done(env, output), [0], done=True)[0]
    assert got == pytest.approx(reward, abs=0.01) and not interrupted


def test_hallway_is_laid_out_as_the_symbol_finder_area():
    """As ``HallwayAgent.OnEpisodeBegin`` places things (x along the hallway): the agent
    at x in [-20, -10], the symbol ahead of it at x in [-5, 5] (the orange O anywhere
    within 3 across, the red X on the middle line), the goals at the far end, 15 or more
    beyond the symbol: past it, the agent sees neither (rays reach 12)."""
    from unitysim.envs.hallway import GOAL_CENTRES, RAY_LENGTH, SYMBOL

    env = make("Hallway", num_areas=8)  # 128 hallways
    env.reset()
    symbol = env.centres[:, SYMBOL]
    assert (env.pos[:, 0] >= -20).all() and (env.pos[:, 0] <= -10).all()
    assert (np.abs(env.pos[:, 1]) <= 3).all()
    assert (np.abs(symbol[:, 0]) <= 5).all() and (np.abs(symbol[:, 1]) <= 3).all()
    assert (symbol[env.red, 1] == 0).all() and np.abs(symbol[~env.red, 1]).max() > 1
    assert (GOAL_CENTRES[:, 0] - 2.0 - symbol[:, 0].max() > RAY_LENGTH).all()
    assert 0.3 < env.red.mean() < 0.7 and 0.3 < env.orange_up.mean() < 0.7


def test_hallways_symbol_and_walls_stop_the_agent():
    """The symbol is a 4-wide block the agent walks round, not through; at 4.5 a decision
    at most, the agent runs the hallway's 49.5 in under 15 decisions."""
    from unitysim.envs.hallway import SYMBOL

    env = make("Hallway")
    output = env.reset()
    env.centres[0, SYMBOL] = (0.0, 0.0)
    env.pos[0], env.heading[0], env.velocity[0] = (-6.0, 0.0), 0.0, 0.0
    forward = idle(env, output)  # agent 0 forward, the others still
    forward["Hallway?team=0"].discrete[0, 0] = 1
    for _ in range(5):
        output = env.step(forward)
    assert env.pos[0, 0] == pytest.approx(-1.0)  # against the block's face (0.5 + 0.5)
    assert env.velocity[0, 0] == 0.0
    env.centres[0, SYMBOL] = (100.0, 100.0)  # out of the way: down to the far wall
    for _ in range(15):
        output = env.step(forward)
    assert env.pos[0, 0] == pytest.approx(24.25)  # the far wall, between the goals


def test_pyramids_switch_then_pyramid_gives_two():
    env = make("Pyramids")
    output = env.reset()
    env.pos[0] = env.objects[0, 0]  # on the switch
    output = env.step(idle(env, output))
    assert env.switched[0] and output["Pyramids?team=0"].obs[3][0, 0] == 1.0
    env.pos[0] = env.objects[0, 1]  # at the pyramid
    (got, _, _) = rows_of(step_until_done(env, output), [0], done=True)[0]
    assert got == pytest.approx(2.0, abs=0.01)


def test_pyramids_spawn_areas_hold_one_thing_each_and_walls_and_stones_stop_the_agent():
    """As ``PyramidAgent.OnEpisodeBegin``: agent, switch, the pyramid's area and six stone
    pyramids in the nine spawn areas, shuffled per area; walking into a stone or a wall
    slides along it."""
    from unitysim.envs.arena import FAR
    from unitysim.envs.pyramids import RADIUS, SIZES, SPAWN, STONES, SWITCH

    env = make("Pyramids")
    output = env.reset()

    def area(points: np.ndarray) -> np.ndarray:
        cell = np.clip(np.floor(points / SPAWN + 1.5), 0, 2).astype(int)
        return cell[..., 0] + 3 * cell[..., 1]

    taken = np.column_stack([area(env.pos), area(env.objects[:, [SWITCH, *range(2, 8)]])])
    taken = np.column_stack([taken, env.pyramid_area])
    assert (np.sort(taken, axis=1) == np.arange(9)).all()  # each area once, every time
    assert len({tuple(row) for row in taken}) > 1  # shuffled per area
    forward = idle(env, output)
    forward["Pyramids?team=0"].discrete[:2, 0] = 1
    env.objects[:2] = FAR  # nothing else in the way: one stone, in the middle room
    stone, reach = np.array([0.0, 0.0]), SIZES[STONES][0, 0] + RADIUS
    env.objects[0, 2] = stone
    env.pos[0], env.heading[0] = stone - (reach + 2.0, 0.3), 0.0  # west of it, facing east
    env.pos[1], env.heading[1] = (12.0, 5.0), np.pi / 2  # below the wall on y = 16.5
    for _ in range(6):
        output = env.step(forward)
    assert env.pos[0, 0] == pytest.approx(stone[0] - reach)  # against the stone's west side
    assert env.pos[0, 1] == pytest.approx(stone[1] - 0.3)
    assert env.pos[1, 1] == pytest.approx(16.0 - RADIUS) and env.velocity[1, 1] == 0.0


def test_dungeon_escape_kill_key_door():
    env = make("DungeonEscape")
    output = env.reset()
    env.pos[0] = env.things[0, 2]  # agent 0 walks into the dragon
    output = step_until_done(env, output)
    assert rows_of(output, [0, 1, 2], done=True).keys() == {0}
    assert not env.alive[0] and env.things[0, 1, 0] < 100  # the key lies where the dragon was
    while 0 in output["DungeonEscape?team=0"].agent_id[~output["DungeonEscape?team=0"].done]:
        output = env.step(idle(env, output))
    env.pos[1] = env.things[0, 1]  # agent 1 picks up the key ...
    output = env.step(idle(env, output))
    assert env.has_key[1]
    env.pos[1] = (6.5, 0.0)  # ... and opens the door
    done = rows_of(step_until_done(env, output), [0, 1, 2], done=True)
    assert done.keys() == {1, 2}
    assert all(group == 1.0 and not interrupted for _, group, interrupted in done.values())
    while True:
        output = env.step(idle(env, output))
        infos = output["DungeonEscape?team=0"]
        if (~infos.done).any():
            break
    group_one = infos.agent_id[~infos.done & (infos.group_id == 1)].tolist()
    assert group_one == [36, 1, 2]  # the sacrificed agent is back as a new agent


def test_walljump_heights_follow_the_environment_parameters_as_the_curriculum_sets_them():
    """``WallJump_curriculum.yaml`` moves ``big_wall_height`` and ``small_wall_height``
    through its lessons: each agent's wall is read from them at its episode begin (a
    sampler drawn once per agent), in Unity units scaled by 1/4."""
    draws = np.random.default_rng(3)
    params = Parameters({"small_wall_height": 1.5, "big_wall_height": lambda: draws.uniform(0, 4)})
    env = load("WallJump")(np.random.default_rng(0), 1, params)
    env.reset()
    for _ in range(3):  # later episode begins draw every configuration
        env._begin(np.ones(len(env.wall), dtype=bool))
        small = env.beh == SMALL
        walls = env.wall * 4.0
        assert set(np.round(walls[small], 6)) <= {0.0, 1.5}
        big = walls[~small]
        assert len(big) and (big >= 0).all() and (big <= 4).all() and len(set(big)) == len(big)
