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
