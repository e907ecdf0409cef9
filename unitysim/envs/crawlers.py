"""Crawler and Worm: jointed bodies that crawl to a target cube (ML-Agents examples).

Both are laid out from release 21's ``Crawler`` / ``Worm`` prefabs and scenes and
``CrawlerAgent`` / ``WormAgent``: ten platforms with one agent each (ids 0..9, no
groups), deciding every 5 physics steps, MaxStep 5000 (then interrupted); a target cube
on the platform that pays +1 when touched (``TouchedTarget``) and moves elsewhere. The
orientation cube sits on the body and faces the target; observations are in its frame
(Unity's: x right, y up, z forward).

**Crawler**: a body and four legs of an upper and a lower part (9 rigid bodies). 20
continuous actions: two target angles for each upper leg (0-7), one for each lower leg
(8-11), then a strength for each upper (12-15) and lower leg (16-19). Each episode draws
the speed to match from [0.1, 15]. Reward each physics step: the velocity match of the
body's velocity with that speed towards the target, times ((cos of the angle between
facing and the target direction) + 1) / 2. Sensors, sorted by name as Unity sorts them:

- ``PhysicsBodySensor:Body`` (126), the prefab's RigidBodySensorComponent with the
  orientation cube as virtual root: for the 9 bodies, model-space position (3) and
  rotation (4) each, then their model-space velocities (3 each), then their local
  rotations (4 each);
- ``VectorSensor_size32``: the distance between goal and actual velocity, the velocity
  (3) and goal velocity (3) in the cube's frame, the rotation from facing to the target
  direction (4), the target's position (3), the height under the body / 10, then the
  body's ground contact and, per leg part, its contact and strength.

**Worm**: four segments in a chain, a joint of two angles between each pair (on
segments 0-2). 9 continuous actions: two target angles per joint (0-5), then their
strengths (6-8). The speed to match is 10; reward: the velocity match of the head
(segment 0) times a facing term, 1 - angle / 180 degrees when the head is within 30
degrees of the target direction, else 0. ``VectorSensor_size64``: the height under the
head / 10, the goal velocity (3), the head's angle from the cube / 180, the rotation to
the target direction (4), the target's position (3), then per segment its contact,
velocity (3) and angular velocity (3); past the head its position relative to the head
(3) and local rotation (4); for segments with a joint, its strength.

Simplified (:mod:`unitysim.envs.jointed`'s reduced model): the pose of the joints moves
the body through a fixed map, the parts keep a rest layout bent by their joints, and a
body cannot fall or flip; the Worm never drops through the floor, so only MaxStep ends an
episode.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import ClassVar

import numpy as np

from unitysim.envs.arena import ArenaEnv
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor
from unitysim.envs.jointed import Glide, Joints, pose_map, quaternion, velocity_match

HALF = 20.0
MAX_STEP = 5000
TOUCH = 1.5  # the body reaches the target cube within this
RAY = 10.0  # the downward ray's length


def wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def in_cube(planar: np.ndarray, goal: np.ndarray, up: np.ndarray | float = 0.0) -> np.ndarray:
    """Vectors on the field (complex, ``goal`` the cube's bearing, broadcast against it)
    in the cube's frame: (..., 3) right, up, forward."""
    turned = planar * np.exp(-1j * goal)
    return np.stack(np.broadcast_arrays(-turned.imag, up, turned.real), axis=-1)


class Crawling(ArenaEnv):
    """Bodies of ``joint_count`` two-angle joints whose pose moves them through ``mix``."""

    fields_per_area = 10
    joint_count: ClassVar[int]
    max_speed: ClassVar[float]
    mix: ClassVar[np.ndarray]  # (2 * joint_count, 3): forward, left, turn

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.body = Glide(self.n, HALF)
        self.joints = Joints(self.n, self.joint_count)
        self.speed = np.full(self.n, self.max_speed)  # the speed to match

    def _begin(self, which: np.ndarray) -> None:
        self.body.begin(which, self.rng)
        self.joints.begin(which)
        self.body.place_targets(which, self.rng)

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        self.joints.step()
        effect = np.tanh(self.joints.pose() @ self.mix)
        self.body.step(effect[:, 0] + 1j * effect[:, 1], effect[:, 2], self.max_speed)
        distance, direction = self.body.to_target()
        match = velocity_match(self.body.velocity, self.speed * direction, self.speed)
        self.reward += match * self._facing(direction)
        touched = distance < TOUCH
        if touched.any():
            self.reward[touched] += 1.0
            self.body.place_targets(touched, self.rng)
        interrupted = self.episode_steps >= MAX_STEP
        return interrupted, interrupted.copy()

    @abstractmethod
    def _facing(self, direction: np.ndarray) -> np.ndarray:
        """The facing term of the reward, per agent (``direction`` to the target)."""

    def _cube(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(bearing of the cube, distance to the target, turn from facing to the cube as
        Unity measures it: clockwise) of ``rows``."""
        way = self.body.target[rows] - self.body.pos[rows]
        goal = np.angle(way)
        return goal, np.abs(way), wrap(self.body.heading[rows] - goal)


# --- Crawler ---------------------------------------------------------------------------

LEGS = 4
CRAWLER_SPEED = 15.0  # m_maxWalkingSpeed
BODY_HEIGHT = 0.6
UPPER, LOWER = 0.6, 1.3  # distance of each leg part's centre from the body's
LEG_BEARING = np.radians([45.0, -45.0, 135.0, -135.0])  # counter-clockwise from forward


class Crawler(Crawling):
    name = "Crawler"
    behaviors = (
        Behavior(
            "Crawler?team=0",
            (
                Sensor.vector("PhysicsBodySensor:Body", 126),
                Sensor.vector("VectorSensor_size32", 32),
            ),
            20,
        ),
    )
    joint_count = 2 * LEGS  # upper legs 0-3, lower legs 4-7 (their second angle stays 0)
    max_speed = CRAWLER_SPEED
    mix = pose_map(1618, 4 * LEGS, 3, 2 * LEGS)

    def _begin(self, which: np.ndarray) -> None:
        super()._begin(which)
        self.speed[which] = self.rng.uniform(0.1, CRAWLER_SPEED, int(which.sum()))

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        a = np.clip(actions.continuous, -1.0, 1.0)
        targets = np.zeros((len(rows), 2 * LEGS, 2))
        targets[:, :LEGS] = a[:, : 2 * LEGS].reshape(-1, LEGS, 2)
        targets[:, LEGS:, 0] = a[:, 2 * LEGS : 3 * LEGS]
        self.joints.drive(rows, targets, a[:, 3 * LEGS :])

    def _facing(self, direction: np.ndarray) -> np.ndarray:
        return ((self.body.facing() * direction.conj()).real + 1.0) / 2.0

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        k, body, joints = len(rows), self.body, self.joints
        goal, distance, turn = self._cube(rows)
        q = joints.q[rows]
        upper, lower = q[:, :LEGS], q[:, LEGS:, 0]
        reach = upper[..., 0] + lower  # how far down each foot presses
        height = BODY_HEIGHT + 0.15 * np.tanh(reach).mean(axis=1)
        # the 9 bodies (body, then upper and lower part of each leg) on the field
        bearing = LEG_BEARING + 0.5 * upper[..., 1]  # (k, legs)
        spoke = np.exp(1j * (body.heading[rows, None] + bearing))
        offset = bodies(0j, UPPER * spoke, LOWER * spoke)
        rise = bodies(0.0, -0.2 * np.sin(upper[..., 0]), -0.5 * np.sin(reach))
        position = in_cube(offset, goal[:, None], rise)
        yaw, pitch = bodies(0.0, -bearing, -bearing), bodies(0.0, upper[..., 0], reach)
        rotation = quaternion(yaw - turn[:, None], pitch, np.zeros_like(pitch))  # Unity's yaw
        spin = body.turn_rate[rows, None]
        velocity = in_cube(body.velocity[rows, None] + 1j * spin * offset, goal[:, None])
        local_yaw = bodies(-body.heading[rows, None], -upper[..., 1], np.zeros_like(lower))
        local_pitch = bodies(0.0, upper[..., 0], lower)
        local = quaternion(local_yaw, local_pitch, np.zeros_like(local_pitch))
        physics = np.concatenate(
            [
                np.concatenate([position, rotation], axis=2).reshape(k, -1),
                velocity.reshape(k, -1),
                local.reshape(k, -1),
            ],
            axis=1,
        )
        # the agent's own observations
        speed = self.speed[rows]
        moving = body.velocity[rows]
        goal_velocity = speed * np.exp(1j * goal)
        touching = leg_parts(upper[..., 0] > 0.9, reach > -0.5)
        strength = leg_parts(joints.strength[rows, :LEGS], joints.strength[rows, LEGS:])
        legs = np.stack([touching, strength], axis=2)  # per leg part: contact, strength
        vector = np.concatenate(
            [
                np.abs(goal_velocity - moving)[:, None],
                in_cube(moving, goal),
                np.column_stack([np.zeros(k), np.zeros(k), speed]),
                quaternion(turn, np.zeros(k), np.zeros(k)),
                np.column_stack([np.zeros(k), 0.5 - height, distance]),
                (height / RAY)[:, None],
                (height < 0.35)[:, None].astype(float),
                legs.reshape(k, -1),
            ],
            axis=1,
        )
        return [physics, vector]


def leg_parts(upper: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """(k, 8): each leg's upper part's value, then its lower part's (``upper``, ``lower``
    (k, legs))."""
    return np.stack([upper, lower], axis=2).reshape(len(upper), -1)


def bodies(first: complex | np.ndarray, upper: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """(k, 9): a value for each of the Crawler's bodies, the body's (``first``), then
    :func:`leg_parts`."""
    legs = leg_parts(upper, lower)
    head = np.broadcast_to(np.asarray(first, dtype=legs.dtype), (len(legs), 1))
    return np.concatenate([head, legs], axis=1)


# --- Worm ------------------------------------------------------------------------------


def from_head(per_joint: np.ndarray) -> np.ndarray:
    """(k, segments): the sum of ``per_joint`` (k, joints) over the joints between the
    head and each segment (0 for the head)."""
    summed = np.cumsum(per_joint, axis=1)
    return np.concatenate([np.zeros((len(summed), 1), summed.dtype), summed], axis=1)


SEGMENTS = 4
WORM_SPEED = 10.0  # m_MaxWalkingSpeed
SEGMENT = 0.6  # distance between segment centres
HEAD_HEIGHT = 0.3
FACING = np.radians(30.0)  # the facing reward's cone


class Worm(Crawling):
    name = "Worm"
    behaviors = (Behavior("Worm?team=0", (Sensor.vector("VectorSensor_size64", 64),), 9),)
    joint_count = SEGMENTS - 1  # joint j joins segment j to segment j + 1
    max_speed = WORM_SPEED
    mix = pose_map(1414, 2 * (SEGMENTS - 1), 3, SEGMENTS - 1)

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        a = np.clip(actions.continuous, -1.0, 1.0)
        joints = SEGMENTS - 1
        self.joints.drive(rows, a[:, : 2 * joints].reshape(-1, joints, 2), a[:, 2 * joints :])

    def _facing(self, direction: np.ndarray) -> np.ndarray:
        angle = np.abs(wrap(self.body.heading - np.angle(direction)))
        return np.where(angle < FACING, 1.0 - angle / np.pi, 0.0)

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        k, body, joints = len(rows), self.body, self.joints
        goal, distance, turn = self._cube(rows)
        q, q_rate = joints.q[rows], joints.q_rate[rows]
        # each segment's heading and pitch: the head's, then bent by each joint in turn
        heading = body.heading[rows, None] + from_head(q[..., 1])  # (k, segments)
        pitch = from_head(q[..., 0])
        bend_rate, pitch_rate = from_head(q_rate[..., 1]), from_head(q_rate[..., 0])
        # centres trail the head, each a segment's length behind the one before
        offset = -from_head(np.exp(1j * heading[:, 1:]) * SEGMENT * np.cos(pitch[:, 1:]))
        rise = from_head(SEGMENT * np.sin(pitch[:, 1:]))
        spin = body.turn_rate[rows, None] + bend_rate
        velocity = in_cube(body.velocity[rows, None] + 1j * spin * offset, goal[:, None])
        angular = np.stack([pitch_rate, -spin, np.zeros_like(spin)], axis=2)
        touching = (np.abs(pitch) < 0.5).astype(float)[..., None]
        position = in_cube(offset, goal[:, None], rise)
        local = quaternion(-heading, pitch, np.zeros_like(pitch))
        strength = joints.strength[rows]
        head = np.concatenate(
            [touching[:, 0], velocity[:, 0], angular[:, 0], strength[:, :1]], axis=1
        )
        parts = [head]
        for s in range(1, SEGMENTS):
            jointed = [strength[:, s : s + 1]] if s < SEGMENTS - 1 else []
            parts.append(
                np.concatenate(
                    [
                        touching[:, s],
                        *(velocity[:, s], angular[:, s], position[:, s], local[:, s]),
                        *jointed,
                    ],
                    axis=1,
                )
            )
        height = HEAD_HEIGHT + 0.1 * np.tanh(pitch[:, 1])
        vector = np.concatenate(
            [
                (height / RAY)[:, None],
                np.column_stack([np.zeros(k), np.zeros(k), np.full(k, WORM_SPEED)]),
                (np.abs(turn) / np.pi)[:, None],
                quaternion(turn, np.zeros(k), np.zeros(k)),
                np.column_stack([np.zeros(k), -height, distance]),
                *parts,
            ],
            axis=1,
        )
        return [vector]
