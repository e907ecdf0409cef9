"""SoccerTwos: two teams of two on eight pitches, laid out and moving as the real example.

The build announces ``SoccerTwos?team=1`` before ``SoccerTwos?team=0``, and numbers the
agents of a pitch purple, blue, purple, blue (ids 0..3; group 2 for purple, 1 for blue,
then 4 and 3 on the next pitch), as the reference dump shows. Each agent sees 11 rays
over ±60° ahead and 3 over ±45° behind, 20 long, cast as spheres of radius 0.5, with 6
tags each (ball, own goal, opposing goal, wall, teammate, opponent; the real build names
goals and agents by colour, here they are relative to the observer so one policy serves
both sides), 3 frames stacked: 264 + 72.

The pitch follows ML-Agents' ``SoccerFieldTwos`` prefab and ``AgentSoccer`` /
``SoccerEnvController`` (Release 21; the prefab's YAML read as text): 31 by 15, goals 8.4
wide; an agent is a rigid body (drag 3) pushed by a velocity change of 2 a physics step,
along its facing (forward and back) or, replacing that, at 0.3 across (no diagonals),
turning 100° a second; at reset the agents start 3.2 to 13.2 from the centre line, ±1.2
across, facing the other goal ±10°, the ball within ±2.5 of the centre. The ball (radius
0.62 at ``ball_scale`` 7.5, mass 3, drag 1) bounces off the 50-kg agents and the walls
with restitution 0.8, and an agent that meets it while its forward action is on kicks it
(2000 N for a physics step: +13.3). Simplified: no angled corner walls, agents pass
through each other, ``gravity`` has no effect (the real ball's height is frozen too).

Rules (``BallGame``): a goal gives the scoring team's group 1 minus the time penalty
(steps so far / MaxEnvironmentSteps) and the other group -1, and ends the pitch's episode
for all four; MaxEnvironmentSteps 5000 interrupts it. Blue (team 0) attacks +x. No
existential reward. ``ball_touch`` (0) rewards 0.2 times it per touch.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import AXIS, DT, stop_at_edge
from unitysim.envs.ball_game import BallGame
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor
from unitysim.envs.perception import Rays

BALL, OWN_GOAL, OPPOSING_GOAL, WALL, TEAMMATE, OPPONENT = range(6)
TEAMS = (1, 0, 1, 0)  # team of each agent of a pitch, in id order
PUSH = 2.0  # agentRunSpeed: a velocity change per physics step
LATERAL = 0.3  # m_LateralSpeed of a generic player (m_ForwardSpeed 1)
AGENT_DRAG, BALL_DRAG = 3.0, 1.0
TURN = np.radians(100.0)  # a second
AGENT_MASS, BALL_MASS = 50.0, 3.0
BOUNCE = 0.8  # restitution of the ball's material (max combine)
KICK = 2000.0 * DT / BALL_MASS  # kickPower's force for one physics step, as a velocity
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
    half = (15.5, 7.5)
    goal_half_width = 4.2
    cast_radius = 0.5
    ball_per_scale = 0.624 / 7.5
    start = ((8.19, 1.2, np.pi), (-8.19, 1.2, 0.0), (8.19, -1.2, np.pi), (-8.19, -1.2, 0.0))
    start_spread = (5.0, 0.0)
    heading_spread = float(np.radians(10.0))
    ball_spread = 2.5
    tags = _tags()
    rays = ((FORWARD, BACKWARD), (FORWARD, BACKWARD))

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.velocity = np.zeros((self.n, 2))  # per second, the world's frame
        self.command = np.zeros((self.n, 3))  # forward, right, left turn: -1, 0 or 1
        self.touching = np.zeros(self.n, dtype=bool)  # in contact with the ball

    def _still(self, rows: np.ndarray) -> None:
        self.velocity[rows] = 0.0
        self.command[rows] = 0.0
        self.touching[rows] = False

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        self.command[rows] = AXIS[np.clip(actions.discrete, 0, 2)]  # forward, right, left turn

    def _move(self) -> None:
        """``AgentSoccer.MoveAgent`` each physics step, then the rigid body's step."""
        forward, right, left = self.command.T
        self.heading += left * TURN * DT
        cos, sin = np.cos(self.heading), np.sin(self.heading)
        across = right != 0.0  # a lateral action replaces the forward one
        push = np.where(across, LATERAL * right, forward)
        self.velocity[:, 0] += PUSH * push * np.where(across, sin, cos)
        self.velocity[:, 1] += PUSH * push * np.where(across, -cos, sin)
        self.velocity /= 1.0 + AGENT_DRAG * DT
        self.pos += self.velocity * DT
        stop_at_edge(self.pos, self.velocity, (self.low, self.high))

    def _kick(self) -> None:
        """A collision of the ball with the first agent it overlaps on each pitch: it
        bounces off (restitution 0.8, the masses' share each), and an agent whose forward
        action is on kicks it when the contact begins (``OnCollisionEnter``)."""
        touch, kicked, row, normal = self._touches()
        began = touch.ravel() & ~self.touching
        self.touching = touch.ravel()
        if len(kicked) == 0:
            return
        closing = np.einsum("fk,fk->f", self.ball_vel[kicked] - self.velocity[row], normal)
        impulse = np.minimum(closing, 0.0) * (1.0 + BOUNCE) / (AGENT_MASS + BALL_MASS)
        self.ball_vel[kicked] -= (impulse * AGENT_MASS)[:, None] * normal
        self.velocity[row] += (impulse * BALL_MASS)[:, None] * normal
        kick = began[row] & (self.command[row, 0] > 0)
        self.ball_vel[kicked] += (kick * KICK)[:, None] * normal
        self.reward[row] += 0.2 * self.ball_touch * began[row]

    def _roll(self) -> None:
        self.ball_vel /= 1.0 + BALL_DRAG * DT
        self.ball += self.ball_vel * DT
