"""SoccerTwos: two teams of two on eight pitches (the ML-Agents example, spec-faithful).

The build announces ``SoccerTwos?team=1`` before ``SoccerTwos?team=0``, and numbers the
agents of a pitch purple, blue, purple, blue (ids 0..3; group 2 for purple, 1 for blue,
then 4 and 3 on the next pitch), as the reference dump shows. Each agent sees 11 rays
over ±60° ahead and 3 over ±45° behind, 6 tags each (ball, own goal, opposing goal, wall,
teammate, opponent; the real build names goals and agents by colour, here they are
relative to the observer so one policy serves both sides), 3 frames stacked: 264 + 72.

Rules (``BallGame``): a goal gives the scoring team's group 1 minus the time penalty
(steps so far / MaxEnvironmentSteps) and the other group -1, and ends the pitch's episode
for all four; MaxEnvironmentSteps 5000 interrupts it. Blue (team 0) attacks +x. No
existential reward. Environment parameters: ``ball_scale`` (7.5), ``gravity`` (9.81),
``ball_touch`` (0: reward 0.2 x ball_touch for touching the ball).
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.ball_game import BallGame
from unitysim.envs.base import Behavior, Sensor
from unitysim.envs.perception import Rays

BALL, OWN_GOAL, OPPOSING_GOAL, WALL, TEAMMATE, OPPONENT = range(6)
TEAMS = (1, 0, 1, 0)  # team of each agent of a pitch, in id order
FORWARD = Rays(5, 60.0, 20.0, 6)
BACKWARD = Rays(1, 45.0, 20.0, 6, backward=True)


def _tags() -> np.ndarray:
    rows = []
    for me in TEAMS:
        left, right = (OWN_GOAL, OPPOSING_GOAL) if me == 0 else (OPPOSING_GOAL, OWN_GOAL)
        players = [TEAMMATE if team == me else OPPONENT for team in TEAMS]
        rows.append([BALL, left, right, *players, WALL])
    return np.array(rows)


def _behavior(team: int, colour: str) -> Behavior:
    return Behavior(
        f"SoccerTwos?team={team}",
        (
            Sensor.vector(f"StackingSensor_size3_{colour}RayPerceptionSensor", 3 * FORWARD.size),
            Sensor.vector(
                f"StackingSensor_size3_{colour}RayPerceptionSensorReverse", 3 * BACKWARD.size
            ),
        ),
        branches=(3, 3, 3),
    )


class SoccerTwos(BallGame):
    name = "SoccerTwos"
    behaviors = (_behavior(1, "Purple"), _behavior(0, "Blue"))
    team_of = (1, 0)
    existential = (0.0, 0.0)
    fields_per_area = 8
    layout = ((0, 2), (1, 1), (0, 2), (1, 1))
    start = ((4.0, 2.0, np.pi), (-4.0, 2.0, 0.0), (4.0, -2.0, np.pi), (-4.0, -2.0, 0.0))
    tags = _tags()
    rays = ((FORWARD, BACKWARD), (FORWARD, BACKWARD))
