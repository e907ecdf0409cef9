"""The arena environments' shared sensors (``unitysim.envs.perception``), at unit level."""

from __future__ import annotations

import numpy as np

from unitysim.envs.perception import FrameStack, Rays, perceive


def test_rays_see_the_nearest_box_or_the_edge():
    sensor = Rays(1, 90.0, 10.0, 2)  # ahead, right, left; tags 0 and 1
    centers = np.array([[[5.0, 0.0], [3.0, 0.0], [0.0, 4.0]]])  # behind the second: hidden
    lo, hi = centers - 0.5, centers + 0.5
    table = np.array([[0, 1, 0, -1]])  # the edge is untagged
    (features,) = perceive((sensor,), np.zeros((1, 2)), np.zeros(1), lo, hi, (8.0, 6.0), table)
    ahead, right, left = features.reshape(3, 4)
    np.testing.assert_allclose(ahead, [0, 1, 0, 0.25])  # tag 1 at 2.5 of 10
    np.testing.assert_allclose(right, [0, 0, 0, 0.6])  # untagged edge at 6
    np.testing.assert_allclose(left, [1, 0, 0, 0.35])  # tag 0 at 3.5
    far = perceive(
        (Rays(0, 0.0, 1.0, 2),), np.zeros((1, 2)), np.zeros(1), lo, hi, (8.0, 6.0), table
    )
    np.testing.assert_allclose(far[0], [[0, 0, 1, 1]])  # nothing within reach

    stack = FrameStack(2, 3, 1)
    rows = np.array([1])
    for value in (1.0, 2.0):
        last = stack.push(rows, np.array([[value]], dtype=np.float32))
    np.testing.assert_array_equal(last, [[0.0, 1.0, 2.0]])  # oldest first, zeros before
