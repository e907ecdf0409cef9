"""What agents on an arena field sense: RayPerceptionSensor-like rays and stacked frames.

Why a module of its own: the spec-faithful environments (:mod:`unitysim.envs.arena`) share
their sensors, which are plain geometry on numpy arrays (no agents, no Academy loop) and the
bulk of their cost, and tests exercise them directly:

- :func:`cast_rays` / :func:`ray_features`: RayPerceptionSensor-like vectors. Rays fan out
  as Unity's (centre first, then right/left pairs); each ray reports a one-hot tag of what
  it hit, a "missed" flag and the hit fraction of its length. Objects are axis-aligned
  boxes; the field's edge is hit when nothing nearer is.
- :class:`Rays` and :func:`perceive`: one sensor's fan, and several sensors that see the
  same boxes cast at once.
- :class:`FrameStack`: StackingSensor (oldest frame first, zeros after an episode begins).
- :class:`FirstPerson`: a camera at the agent's eye over a walled square floor with discs
  standing on it (food, other agents), one ray per image column; it gives colour codes
  that each environment maps to its palette.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np


def ray_offsets(rays_per_direction: int, max_degrees: float) -> np.ndarray:
    """Ray angles relative to the facing direction (radians, counter-clockwise positive),
    in Unity's order: straight ahead, then for each step one ray right and one left."""
    steps = np.arange(1, rays_per_direction + 1) * (max_degrees / max(rays_per_direction, 1))
    return np.radians(np.concatenate([[0.0], np.column_stack([-steps, steps]).ravel()]))


def cast_rays(
    origin: np.ndarray,
    heading: np.ndarray,
    offsets: np.ndarray,
    length: float | np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    half: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Cast ``R`` rays from each of ``n`` origins against ``m`` boxes each.

    ``origin`` (n, 2), ``heading`` (n,), ``offsets`` and ``length`` (R,) or scalar, boxes
    ``lo``/``hi`` (n, m, 2) in the same frame as the field ``[-half, half]``. A box
    containing the origin (the agent itself) is not seen. Returns the hit fraction (n, R)
    in [0, 1] (1 = nothing within ``length``) and what was hit (n, R): box index, ``m``
    for the field's edge, -1 nothing.
    """
    n, m = lo.shape[:2]
    angle = (heading[:, None] + offsets).astype(np.float32)
    dx, dy = np.cos(angle), np.sin(angle)
    np.copyto(dx, 1e-9, where=dx == 0.0)  # float32 cosines are never 0 in practice
    np.copyto(dy, 1e-9, where=dy == 0.0)
    ix, iy = 1.0 / dx, 1.0 / dy  # (n, R)
    # Slab test, (n, m, R): box j is entered at ``near`` if near <= far and near >= 0;
    # the corners relative to the origin, lo then hi: (n, 2m) per axis
    rel = (np.concatenate([lo, hi], axis=1) - origin[:, None, :]).astype(np.float32)
    tx = np.ascontiguousarray(rel[:, :, 0])[:, :, None] * ix[:, None, :]
    ty = np.ascontiguousarray(rel[:, :, 1])[:, :, None] * iy[:, None, :]
    tx1, tx2, ty1, ty2 = tx[:, :m], tx[:, m:], ty[:, :m], ty[:, m:]
    near = np.maximum(np.minimum(tx1, tx2), np.minimum(ty1, ty2))
    far = np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2))
    np.putmask(near, (near > far) | (near < 0.0), np.inf)
    best = near.argmin(axis=1)
    t_best = near[np.arange(n)[:, None], best, np.arange(best.shape[1])]
    # where the ray leaves the field: at half * |1/d| - origin / d along each axis
    o = origin.astype(np.float32)
    edge = np.minimum(
        half[0] * np.abs(ix) - o[:, 0, None] * ix, half[1] * np.abs(iy) - o[:, 1, None] * iy
    )
    hit = np.where(t_best < edge, best, m)
    frac = np.minimum(t_best, edge) / np.asarray(length, dtype=np.float32)
    return np.minimum(frac, 1.0), np.where(frac <= 1.0, hit, -1)


def ray_tags(hit: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Tag index of each hit: ``table`` (n, m + 1), last entry for the edge; -1 for no hit
    (or an untagged object)."""
    tags = table[np.arange(len(hit))[:, None], hit]  # hit -1 reads the edge; masked below
    return np.where(hit >= 0, tags, -1)


def ray_features(tag: np.ndarray, frac: np.ndarray, num_tags: int) -> np.ndarray:
    """RayPerceptionOutput as floats: per ray, one-hot tag, missed flag, hit fraction."""
    n, rays = tag.shape
    out = np.empty((n, rays, num_tags + 2), dtype=np.float32)
    np.equal(tag[:, :, None], np.arange(num_tags), out=out[:, :, :num_tags], casting="unsafe")
    out[:, :, num_tags] = frac >= 1.0
    out[:, :, num_tags + 1] = frac
    return out.reshape(n, -1)


@dataclass(frozen=True)
class Rays:
    """One RayPerceptionSensor: its fan of rays, their length and how many tags it detects."""

    rays_per_direction: int
    max_degrees: float
    length: float
    num_tags: int
    backward: bool = False  # the "Reverse" sensors look behind the agent

    @property
    def count(self) -> int:
        return 2 * self.rays_per_direction + 1

    @property
    def offsets(self) -> np.ndarray:
        offsets = ray_offsets(self.rays_per_direction, self.max_degrees)
        return offsets + np.pi if self.backward else offsets

    @property
    def size(self) -> int:
        return self.count * (self.num_tags + 2)


@functools.cache
def _fan(sensors: tuple[Rays, ...]) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    """Offsets and lengths of all rays of ``sensors``, and where each sensor's rays start."""
    offsets = np.concatenate([s.offsets for s in sensors])
    lengths = np.concatenate([np.full(s.count, s.length) for s in sensors])
    return offsets, lengths, tuple(np.cumsum([0] + [s.count for s in sensors]).tolist())


def perceive(
    sensors: tuple[Rays, ...],
    origin: np.ndarray,
    heading: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    half: tuple[float, float],
    table: np.ndarray | tuple[np.ndarray, ...],
) -> list[np.ndarray]:
    """The feature vectors of several ray sensors that see the same boxes, cast at once.

    ``table`` (n, m + 1) maps box index (and last, the edge) to a tag, -1 for none; a tuple
    gives one table per sensor (sensors that see the same things differently)."""
    offsets, lengths, starts = _fan(sensors)
    frac, hit = cast_rays(origin, heading, offsets, lengths, lo, hi, half)
    if isinstance(table, tuple):
        tags = np.concatenate(
            [
                ray_tags(hit[:, a:b], t)
                for (a, b), t in zip(itertools.pairwise(starts), table, strict=True)
            ],
            axis=1,
        )
    else:
        tags = ray_tags(hit, table)
    n, widths = len(tags), {s.num_tags for s in sensors}
    if len(widths) > 1:
        return [
            ray_features(tags[:, a:b], frac[:, a:b], s.num_tags)
            for (a, b), s in zip(itertools.pairwise(starts), sensors, strict=True)
        ]
    (width,) = widths  # one encoding for all rays, then split per sensor
    features = ray_features(tags, frac, width).reshape(n, -1, width + 2)
    return [features[:, a:b].reshape(n, -1) for a, b in itertools.pairwise(starts)]


class FrameStack:
    """StackingSensor: the last ``frames`` observations of each agent, oldest first."""

    def __init__(self, n: int, frames: int, size: int) -> None:
        self.size = size
        self.buffer = np.zeros((n, frames * size), dtype=np.float32)

    def push(self, rows: np.ndarray, frame: np.ndarray) -> np.ndarray:
        stacked = np.concatenate([self.buffer[rows, self.size :], frame], axis=1)
        self.buffer[rows] = stacked
        return stacked

    def clear(self, which: np.ndarray) -> None:
        self.buffer[which] = 0.0


SKY, WALL_X, WALL_Y, FLOOR = range(4)  # FirstPerson's scene codes; objects bring their own
# their colours, as k/255 so that PNG is lossless
SCENE_RGB = ((150, 190, 230), (170, 170, 170), (120, 120, 120), (110, 90, 70))


def palette(*objects: tuple[int, int, int]) -> np.ndarray:
    """(codes, 3) RGB in [0, 1]: the scene's colours, then ``objects``' (codes 4, 5, ...)."""
    return np.array([*SCENE_RGB, *objects], dtype=np.float32) / np.float32(255.0)


@dataclass(frozen=True)
class FirstPerson:
    """A pinhole camera of ``size`` x ``size`` pixels and a horizontal field of view of
    ``fov_degrees``, ``eye`` above the floor, looking level along the agent's heading.

    Walls are ``wall_height`` tall on the square's edges, in two shades (one per axis, so
    corners show); each object is a sphere of its radius resting on the floor, drawn as its
    vertical section through the column's ray, the nearest one in front."""

    size: int
    fov_degrees: float
    eye: float
    wall_height: float

    @functools.cached_property
    def _columns(self) -> tuple[float, np.ndarray, np.ndarray]:
        focal = self.size / 2 / np.tan(np.radians(self.fov_degrees) / 2)
        # per column (0 = leftmost): its angle from the heading, counter-clockwise
        offsets = np.arctan((self.size / 2 - (np.arange(self.size) + 0.5)) / focal)
        return float(focal), offsets, np.cos(offsets).astype(np.float32)

    def codes(
        self,
        pos: np.ndarray,
        heading: np.ndarray,
        half: np.ndarray,
        objects: np.ndarray,
        radius: np.ndarray,
        code: np.ndarray,
    ) -> np.ndarray:
        """(k, H, W) uint8 codes: cameras at ``pos`` (k, 2) facing ``heading`` (k,) in
        squares of ``half`` (k,); objects (k, m, 2) of ``radius`` and ``code`` (k, m) each,
        a code < 0 for an absent one."""
        focal, offsets, cos_offsets = self._columns
        horizon = np.float32(self.size / 2)
        rows = (np.arange(self.size, dtype=np.float32) + 0.5)[None, :, None]
        pos = pos.astype(np.float32)
        angle = (heading[:, None] + offsets).astype(np.float32)
        dx, dy = np.cos(angle), np.sin(angle)  # (k, W)
        # walls: where the ray leaves the square, per axis
        half = half[:, None].astype(np.float32)
        tx = (half - pos[:, :1] * np.sign(dx)) / np.maximum(np.abs(dx), 1e-6)
        ty = (half - pos[:, 1:] * np.sign(dy)) / np.maximum(np.abs(dy), 1e-6)
        depth = np.minimum(tx, ty) * cos_offsets
        wall = np.where(tx < ty, WALL_X, WALL_Y).astype(np.uint8)[:, None]
        wall_top = (horizon - focal * (self.wall_height - self.eye) / depth)[:, None]
        wall_bottom = (horizon + focal * self.eye / depth)[:, None]
        image = np.where(rows < wall_top, SKY, np.where(rows < wall_bottom, wall, FLOOR))
        present = code >= 0
        count = int(present.sum(axis=1).max(initial=0))
        if count == 0:
            return image.astype(np.uint8)
        # the objects present first, so that ``count`` columns hold them all
        order = np.argsort(~present, axis=1, kind="stable")[:, :count]
        objects = np.take_along_axis(objects, order[..., None], axis=1)
        radius = np.take_along_axis(radius, order, axis=1).astype(np.float32)[..., None]
        code = np.take_along_axis(code, order, axis=1)
        rel = (objects - pos[:, None]).astype(np.float32)
        along = rel[:, :, :1] * dx[:, None] + rel[:, :, 1:] * dy[:, None]  # (k, count, W)
        aside = rel[:, :, :1] * dy[:, None] - rel[:, :, 1:] * dx[:, None]
        hit = (code[..., None] >= 0) & (along > 0.0) & (aside * aside < radius**2)
        along = np.where(hit, along, np.inf)
        nearest = along.argmin(axis=1)[:, None]  # (k, 1, W)
        distance = np.take_along_axis(along, nearest, axis=1)[:, 0]
        off = np.take_along_axis(aside, nearest, axis=1)[:, 0]
        size = np.take_along_axis(np.broadcast_to(radius, along.shape), nearest, axis=1)[:, 0]
        what = np.take_along_axis(np.broadcast_to(code[..., None], along.shape), nearest, 1)
        chord = np.sqrt(np.maximum(size**2 - off * off, 0.0))  # half the section's height
        seen = np.isfinite(distance)
        z = np.where(seen, distance, 1.0) * cos_offsets
        top = horizon - focal * (size + chord - self.eye) / z
        bottom = horizon + focal * (self.eye - size + chord) / z
        top = np.where(seen, top, np.inf)[:, None]
        inside = (rows >= top) & (rows < bottom[:, None])
        return np.where(inside, what, image).astype(np.uint8)


def colours(codes: np.ndarray, palette_channels: np.ndarray) -> np.ndarray:
    """(k, 3, H, W) images of :meth:`FirstPerson.codes`' (k, H, W), ``palette_channels``
    (3, codes) giving each code's RGB."""
    k, height, width = codes.shape
    pixels = np.take(palette_channels, codes.reshape(k, -1), axis=1)
    return pixels.reshape(3, k, height, width).transpose(1, 0, 2, 3)
