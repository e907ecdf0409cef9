"""Walker: a balancing, 39-action body that must walk towards a target (spec-faithful).

Ten independent walkers (ids 0..9, no groups) on 30 x 30 fields, as in the dump: one
``VectorSensor_size243`` and 39 continuous actions. There is no rigid-body physics here;
the body is :mod:`unitysim.envs.jointed`'s reduced model, which keeps what matters for
learning:

- 13 joints with 2 target angles each (actions 0-25, times 1 rad) and a strength each
  (actions 26-38, from [-1, 1] to [0, 1]); a joint moves towards its target as a
  spring as stiff as its strength.
- The pose drives the body through fixed linear maps (the same for every run): a velocity
  in the body's frame (forward, left), a turn rate, and a torque that keeps the torso up.
  The torso is an inverted pendulum (``gravity``; heavier ``hip_mass``, ``chest_mass``,
  ``spine_mass`` make the torque act slower): left alone it falls, and a walker whose
  torso tilts more than 0.8 rad has fallen, which ends its episode (not interrupted).
- A target cube sits on the field; reaching it (within 1.5) moves it elsewhere.

Reward, as ``WalkerAgent`` adds it every physics step: the product of the velocity match
((1 - (|v - v_goal| / 3)^2)^2, clamped, v_goal = 3 m/s towards the target) and the facing
term ((cos of the angle between facing and the target direction + 1) / 2), both in [0, 1].
MaxStep 5000 (interrupted).

Observation (243): for each of the 16 body parts (hips, chest, spine, head, thigh, shin,
foot x2, upper arm, forearm, hand x2), 15 values in the frame that faces the target:
ground contact, velocity (3), angular velocity (3), position relative to the hips (3),
rotation quaternion (4), joint strength; then the target speed, the velocity error and
the distance to the target.
"""

from __future__ import annotations

import numpy as np

from unitysim.envs.arena import DT, ArenaEnv
from unitysim.envs.base import Actions, Behavior, Parameters, Sensor
from unitysim.envs.jointed import Glide, Joints, pose_map, quaternion, velocity_match

HALF = 15.0
JOINTS, PARTS = 13, 16
MAX_STEP = 5000
WALK_SPEED, MAX_SPEED = 3.0, 4.0
PENDULUM = 2.0  # length of the inverted pendulum (m)
BALANCE, TILT_DAMPING, FALLEN = 12.0, 1.0, 0.8
HIP_HEIGHT = 1.1
# body parts: parent part and the joint that moves each part relative to it (-1: none)
PARENT = (-1, 2, 0, 1, 0, 4, 5, 0, 7, 8, 1, 10, 11, 1, 13, 14)
JOINT = (-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, -1, 11, 12, -1)
# rest position of each part relative to the hips: forward, up, left
REST = np.array(
    [
        [0.0, 0.0, 0.0], [0.0, 0.55, 0.0], [0.0, 0.3, 0.0], [0.0, 0.9, 0.0],
        [0.0, -0.3, 0.15], [0.0, -0.7, 0.15], [0.1, -1.05, 0.15],
        [0.0, -0.3, -0.15], [0.0, -0.7, -0.15], [0.1, -1.05, -0.15],
        [0.0, 0.55, 0.35], [0.0, 0.3, 0.4], [0.0, 0.05, 0.4],
        [0.0, 0.55, -0.35], [0.0, 0.3, -0.4], [0.0, 0.05, -0.4],
    ]
)  # fmt: skip


def _chain() -> np.ndarray:
    """(parts, joints): 1 where a joint lies between the hips and the part."""
    chain = np.zeros((PARTS, JOINTS))
    for part in range(PARTS):
        walk = part
        while walk > 0:
            if JOINT[walk] >= 0:
                chain[part, JOINT[walk]] = 1.0
            walk = PARENT[walk]
    return chain


CHAIN = _chain()
# fixed maps from the pose to motion, the same in every run: the torso's torque (pitch,
# roll), the stride in the body frame (forward, left) and the turn rate
MIX = pose_map(2718, 2 * JOINTS, 5, JOINTS)
STRENGTH_OF_PART = np.array([j if j >= 0 else JOINTS for j in JOINT])  # JOINTS -> 1


class Walker(ArenaEnv):
    name = "Walker"
    behaviors = (Behavior("Walker?team=0", (Sensor.vector("VectorSensor_size243", 243),), 39),)
    fields_per_area = 10

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        self.body = Glide(self.n, HALF)
        self.joints = Joints(self.n, JOINTS)
        self.tilt = np.zeros((self.n, 2))  # pitch (forward), roll (left)
        self.tilt_rate = np.zeros((self.n, 2))
        self.gravity, self.inertia = 9.81, 1.0

    def _begin(self, which: np.ndarray) -> None:
        self.gravity = self.params.get("gravity", 9.81)
        masses = [self.params.get(f"{p}_mass", 8.0) for p in ("hip", "chest", "spine")]
        self.inertia = max(sum(masses) / 24.0, 0.1)
        self.body.begin(which, self.rng)
        self.tilt[which] = self.rng.uniform(-0.05, 0.05, (int(which.sum()), 2))
        self.tilt_rate[which] = 0.0
        self.joints.begin(which)
        self.body.place_targets(which, self.rng)

    def _act(self, rows: np.ndarray, actions: Actions) -> None:
        a = np.clip(actions.continuous, -1.0, 1.0)
        self.joints.drive(rows, a[:, : 2 * JOINTS].reshape(-1, JOINTS, 2), a[:, 2 * JOINTS :])

    def _simulate(self) -> tuple[np.ndarray, np.ndarray]:
        self.joints.step()
        effect = np.tanh(self.joints.pose() @ MIX)
        fall = (self.gravity / PENDULUM) * np.sin(self.tilt)
        torque = effect[:, :2] * (BALANCE / self.inertia)
        self.tilt_rate += (fall + torque - TILT_DAMPING * self.tilt_rate) * DT
        self.tilt += self.tilt_rate * DT
        body = self.body
        body.step(effect[:, 2] + 1j * effect[:, 3], effect[:, 4], MAX_SPEED)
        # reward: velocity match times facing the target
        distance, direction = body.to_target()
        match = velocity_match(body.velocity, WALK_SPEED * direction, WALK_SPEED)
        looking = ((body.facing() * direction.conj()).real + 1.0) / 2.0
        self.reward += match * looking
        reached = distance < 1.5
        if reached.any():
            body.place_targets(reached, self.rng)
        fell = np.maximum(np.abs(self.tilt[:, 0]), np.abs(self.tilt[:, 1])) > FALLEN
        interrupted = ~fell & (self.episode_steps >= MAX_STEP)
        return fell | interrupted, interrupted

    def _observe(self, behavior: int, rows: np.ndarray) -> list[np.ndarray]:
        k, body, joints = len(rows), self.body, self.joints
        to_target = body.target[rows] - body.pos[rows]
        distance = np.abs(to_target)
        goal = np.angle(to_target)
        # angles of each part (k, parts): pitch and roll from the torso and its joints,
        # yaw the facing relative to the target direction
        pitch = self.tilt[rows, 0, None] + joints.q[rows, :, 0] @ CHAIN.T
        roll = self.tilt[rows, 1, None] + joints.q[rows, :, 1] @ CHAIN.T
        yaw = np.broadcast_to((body.heading[rows] - goal)[:, None], pitch.shape)
        spin = np.stack(
            [
                self.tilt_rate[rows, 1, None] + joints.q_rate[rows, :, 1] @ CHAIN.T,
                np.broadcast_to(body.turn_rate[rows, None], pitch.shape),
                self.tilt_rate[rows, 0, None] + joints.q_rate[rows, :, 0] @ CHAIN.T,
            ],
            axis=2,
        )
        # each part's position relative to the hips: rest offset turned by pitch, roll, yaw
        x, y, z = REST[:, 0], REST[:, 1], REST[:, 2]
        cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
        x1, y1 = x * cp + y * sp, y * cp - x * sp
        y2, z2 = y1 * cr - z * sr, y1 * sr + z * cr
        cy, sy = np.cos(yaw), np.sin(yaw)
        position = np.stack([x1 * cy - z2 * sy, y2, x1 * sy + z2 * cy], axis=2)
        contact = HIP_HEIGHT * np.cos(self.tilt[rows, 0, None]) + y2 < 0.1
        # velocity in the goal frame: the body's, plus the part's turning about the hips
        relative = body.velocity[rows] * np.exp(-1j * goal)  # along, across the goal direction
        body = np.column_stack([relative.real, np.zeros(k), relative.imag])
        velocity = body[:, None, :] + np.cross(spin, position)
        # rotation quaternion (x, y, z, w) of yaw about up, then pitch, then roll
        rotation = quaternion(yaw, pitch, roll)
        with_jointless = np.column_stack([joints.strength[rows], np.ones(k)])  # column JOINTS
        strength = with_jointless[:, STRENGTH_OF_PART, None]
        parts = np.concatenate(
            [contact[..., None], velocity / MAX_SPEED, spin, position, rotation, strength], axis=2
        )
        error = np.abs(relative - WALK_SPEED)
        extra = np.column_stack(
            [np.full(k, WALK_SPEED / MAX_SPEED), error / WALK_SPEED, distance / 30.0]
        )
        return [np.concatenate([parts.reshape(k, -1), extra], axis=1)]
