"""Jointed bodies without rigid-body physics: what Walker, Crawler and Worm share.

Why a reduced model: unitysim has no physics engine, and what a learner meets in these
examples is JointDriveController's action layout (per joint, target angles from [-1, 1]
and a strength) and a reward for moving at a speed towards a target while facing it.
:class:`Joints` moves each joint towards its target as a spring as stiff as its
strength; :class:`Glide` moves the body on the field at the velocity (in its own frame)
and turn rate its pose sets through a fixed map (:func:`pose_map`, the same in every run),
which the body follows within about 0.2 s.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import DT, uniform_in

STIFFNESS, DAMPING = 120.0, 18.0
FOLLOW = 0.1  # share of the gap to the pose's velocity the body closes per physics step
TURN_RATE = 2.0  # rad/s at full turn
TARGET_AWAY = 5.0  # a new target lands at least about this far from the body


def pose_map(seed: int, inputs: int, outputs: int, joints: int) -> np.ndarray:
    """A fixed (inputs, outputs) map from the joints' angles to motion, for ``tanh(q @ map)``."""
    return np.random.default_rng(seed).normal(size=(inputs, outputs)) / np.sqrt(joints)


def velocity_match(velocity: np.ndarray, goal: np.ndarray, speed: np.ndarray | float) -> np.ndarray:
    """JointDriveController examples' speed reward, in [0, 1]: 1 at the goal velocity,
    falling as a declining sigmoid to 0 when the two differ by ``speed`` (both complex)."""
    error = np.minimum(np.abs(velocity - goal), speed)
    return (1.0 - (error / speed) ** 2) ** 2


def quaternion(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Unity's (x, y, z, w) of a turn by ``yaw`` about up, then ``pitch``, then ``roll``."""
    hy, hp, hr = yaw / 2.0, pitch / 2.0, roll / 2.0
    ax, ay = np.sin(hy) * np.sin(hp), np.sin(hy) * np.cos(hp)
    az, aw = np.cos(hy) * np.sin(hp), np.cos(hy) * np.cos(hp)
    ch, sh = np.cos(hr), np.sin(hr)
    return np.stack(
        [aw * sh + ax * ch, ay * ch + az * sh, az * ch - ay * sh, aw * ch - ax * sh], axis=-1
    )


class Joints:
    """Per agent, ``joints`` joints of ``dof`` angles each, driven as JointDriveController's."""

    def __init__(self, n: int, joints: int, dof: int = 2) -> None:
        self.q = np.zeros((n, joints, dof))
        self.q_rate = np.zeros((n, joints, dof))
        self.aim = np.zeros((n, joints, dof))  # target angles (rad)
        self.strength = np.ones((n, joints))  # in [0, 1]

    def begin(self, which: np.ndarray) -> None:
        for array in (self.q, self.q_rate, self.aim):
            array[which] = 0.0
        self.strength[which] = 1.0

    def drive(self, rows: np.ndarray, targets: np.ndarray, strengths: np.ndarray) -> None:
        """Actions in [-1, 1]: ``targets`` (k, joints, dof), times 1 rad, and
        ``strengths`` (k, joints)."""
        self.aim[rows] = targets
        self.strength[rows] = (strengths + 1.0) / 2.0

    def step(self) -> None:
        spring = STIFFNESS * self.strength[:, :, None] * (self.aim - self.q)
        self.q_rate += (spring - DAMPING * self.q_rate) * DT
        self.q += self.q_rate * DT

    def pose(self) -> np.ndarray:
        """Every angle of every joint, (n, joints * dof)."""
        return self.q.reshape(len(self.q), -1)


class Glide:
    """Bodies on a square field of half size ``half``; positions and velocities are
    complex (x + 1j * y), headings counter-clockwise from x."""

    def __init__(self, n: int, half: float) -> None:
        self.half = half
        self.pos = np.zeros(n, dtype=complex)
        self.velocity = np.zeros(n, dtype=complex)
        self.target = np.zeros(n, dtype=complex)
        self.heading = np.zeros(n)
        self.turn_rate = np.zeros(n)

    def begin(self, which: np.ndarray, rng: np.random.Generator) -> None:
        """A random place and heading, at rest (the caller then places the targets)."""
        k = int(which.sum())
        self.pos[which] = uniform_in(rng, k, (self.half, self.half), 2.0) @ [1.0, 1j]
        self.heading[which] = rng.uniform(-np.pi, np.pi, k)
        self.velocity[which] = 0.0
        self.turn_rate[which] = 0.0

    def place_targets(self, which: np.ndarray, rng: np.random.Generator) -> None:
        spot = uniform_in(rng, int(which.sum()), (self.half, self.half), 2.0) @ [1.0, 1j]
        close = np.abs(spot - self.pos[which]) < TARGET_AWAY
        spot[close] = -spot[close]  # the other side of the field
        self.target[which] = spot

    def step(self, stride: np.ndarray, turn: np.ndarray, max_speed: float) -> None:
        """One physics step towards ``stride`` (complex, the body's frame: forward + 1j *
        left, times ``max_speed``) while turning at ``turn`` (in [-1, 1]) of full rate."""
        self.turn_rate = turn * TURN_RATE
        self.heading += self.turn_rate * DT
        facing = np.exp(1j * self.heading)
        self.velocity += (facing * stride * max_speed - self.velocity) * FOLLOW
        self.pos += self.velocity * DT
        bounds = self.pos.view(np.float64)
        np.clip(bounds, -self.half, self.half, out=bounds)  # the field is square

    def to_target(self) -> tuple[np.ndarray, np.ndarray]:
        """(distance, unit direction as complex) from each body to its target."""
        way = self.target - self.pos
        distance = np.abs(way)
        return distance, way / np.maximum(distance, 1e-6)

    def facing(self) -> np.ndarray:
        return np.exp(1j * self.heading)
