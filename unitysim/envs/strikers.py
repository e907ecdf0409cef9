"""StrikersVsGoalie: two strikers against a goalie on eight pitches (spec-faithful).

Agents of a pitch are numbered striker, goalie, striker (ids 0..2; the strikers in group
1, the goalie in group 2, then 3 and 4 on the next pitch), as the reference dump shows.
A striker sees 11 rays over ±60° ahead and 3 over ±45° behind with 5 tags (ball, goal,
wall, teammate, goalie), 3 frames stacked: 231 + 63; the goalie sees 41 rays over ±90°
with 4 tags (ball, its goal, wall, striker), 3 frames stacked: 738.

Rules (``BallGame``): only the goalie's goal, at +x, exists; the other end is a wall. A
goal gives the strikers' group 1 minus the time penalty and the goalie's group -1, and
ends the pitch's episode; MaxEnvironmentSteps 5000 interrupts it. Existential rewards as
in ``AgentSoccer``: -1 / MaxEnvironmentSteps per step for a striker, +1 / ... for the
goalie, so a goalie that holds out earns +1. Environment parameters: ``ball_scale``
(7.5), ``gravity`` (9.81), ``ball_touch`` (0).
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.ball_game import BallGame
from unitysim.envs.base import Behavior, Sensor
from unitysim.envs.perception import Rays

STRIKER_FORWARD = Rays(5, 60.0, 20.0, 5)
STRIKER_BACKWARD = Rays(1, 45.0, 20.0, 5, backward=True)
GOALIE = Rays(20, 90.0, 20.0, 4)
# objects: ball, (no goal at -x), goal at +x, striker, goalie, striker; then the walls
TAGS = np.array(
    [
        [0, 2, 1, 3, 4, 3, 2],  # striker: ball, goal, wall, teammate, goalie
        [0, 2, 1, 3, 3, 3, 2],  # goalie: ball, its goal, wall, striker
        [0, 2, 1, 3, 4, 3, 2],
    ]
)


class StrikersVsGoalie(BallGame):
    name = "StrikersVsGoalie"
    behaviors = (
        Behavior(
            "Striker?team=0",
            (
                Sensor.vector(
                    "StackingSensor_size3_BlueRayPerceptionSensor", 3 * STRIKER_FORWARD.size
                ),
                Sensor.vector(
                    "StackingSensor_size3_BlueRayPerceptionSensorReverse",
                    3 * STRIKER_BACKWARD.size,
                ),
            ),
            branches=(3, 3, 3),
        ),
        Behavior(
            "Goalie?team=1",
            (
                Sensor.vector(
                    "StackingSensor_size3_PurpleGoalieRayPerceptionSensor", 3 * GOALIE.size
                ),
            ),
            branches=(3, 3, 3),
        ),
    )
    team_of = (0, 1)
    existential = (-1.0, 1.0)
    goals = (False, True)
    fields_per_area = 8
    layout = ((0, 1), (1, 2), (0, 1))
    start = ((-4.0, 2.0, 0.0), (7.0, 0.0, np.pi), (-4.0, -2.0, 0.0))
    tags = TAGS
    rays = ((STRIKER_FORWARD, STRIKER_BACKWARD), (GOALIE,))
