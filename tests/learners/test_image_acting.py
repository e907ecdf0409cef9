"""The workers' numpy image encoders against the learner's torch ones: the same weights
by name, the same outputs for every type, and initial weights drawn with torch's laws."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from learners.acting.numpy_images import NumpyImageEncoder, initial_encoder_weights
from learners.networks.encoders import MIN_SIZE, visual_encoder


@pytest.mark.parametrize("encoder_type", list(MIN_SIZE))
def test_numpy_and_torch_encoders_agree_on_the_same_weights(encoder_type):
    shape = (3, 40, 36)
    torch.manual_seed(0)
    encoder = visual_encoder(shape, encoder_type, 32)
    drawn = initial_encoder_weights("net", shape, encoder_type, 32, np.random.default_rng(1))
    # the learner's weight names and shapes, as its state_dict has them
    state = {k: v.numpy() for k, v in encoder.state_dict().items()}
    assert {k: v.shape for k, v in drawn.items()} == {f"net.{k}": v.shape for k, v in state.items()}
    pixels = np.random.default_rng(2).integers(0, 256, (5, *shape), dtype=np.uint8)
    with torch.no_grad():
        expected = encoder(torch.from_numpy(pixels)).numpy()
    ours = NumpyImageEncoder(encoder_type, state)(pixels)
    assert ours.shape == (5, 32) and ours.dtype == np.float32
    np.testing.assert_allclose(ours, expected, rtol=1e-4, atol=1e-5)


def test_initial_convolutions_follow_torchs_default_law():
    """Weight and bias uniform in +-1/sqrt(fan in), as torch's Conv2d draws them."""
    drawn = initial_encoder_weights("net", (3, 84, 84), "nature_cnn", 64, np.random.default_rng(0))
    first, dense = drawn["net.body.0.weight"], drawn["net.dense.weight"]
    bound = 1 / np.sqrt(3 * 8 * 8)
    assert np.abs(first).max() <= bound and np.abs(first).max() > 0.95 * bound
    assert abs(first.std() - bound / np.sqrt(3)) < 0.05 * bound  # a uniform's spread
    assert abs(dense.std() * np.sqrt(dense.shape[1]) / 1.41 - 1.0) < 0.02
    assert not drawn["net.dense.bias"].any()
