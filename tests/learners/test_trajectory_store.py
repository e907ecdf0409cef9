"""The PPO learner's trajectory store: each observation once, next observations only at
truncated ends, the estimator equal to torchrl's GAE over full next observations, and a
buffer that cannot fit refused in one line before it is allocated."""

from __future__ import annotations

import pytest
import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec, DimensionProperty, ObservationSpec
from mlagents_envs.base_env import ObservationType as Obs
from torchrl.objectives.value import GAE

from batches import keys
from learners.algorithms.ppo import PPO
from learners.algorithms.trajectory_store import TrajectoryStore
from learners.host.learner import CentralLearner
from learners.networks.policies import ActorCritic
from learners.networks.torchrl_views import add_flat_action, value_operator
from learners.trainer_config.parse import parse_config
from learners.trainer_config.settings import NetworkSettings
from testkit.segments import IMAGE, segment, vector_spec
from tests.learners.test_algorithms import settings


def with_episode_ends(batch, terminated=(), truncated=()):
    """Episodes that end mid-row, each with a final observation of its own."""
    for t in (*terminated, *truncated):
        batch[keys.NEXT, keys.OBS, "vector"][t] = torch.randn(batch[keys.OBS, "vector"][t].shape)
    for t in terminated:
        batch[keys.NEXT, keys.TERMINATED][t] = batch[keys.NEXT, keys.DONE][t] = True
        batch[keys.NEXT, keys.TRUNCATED][t] = False
    for t in truncated:
        batch[keys.NEXT, keys.TRUNCATED][t] = batch[keys.NEXT, keys.DONE][t] = True
    return batch


def test_the_estimate_is_torchrls_gae_over_every_next_observation():
    """Values from a real network, episodes ending terminated and truncated mid-row: the
    store's bootstrap (the next row's value, or a kept end's) gives what torchrl's GAE
    module gives from every step's own next observation."""
    spec = vector_spec(continuous=2)
    torch.manual_seed(0)
    network = ActorCritic(spec, NetworkSettings(hidden_units=32, num_layers=2))
    batch = with_episode_ends(segment(spec, 8, 16, seed=1), terminated=[5, 40], truncated=[70])
    batch[keys.NEXT, keys.REWARD] = torch.randn(128, 1)
    ppo = PPO(network, settings(gamma=0.9, batch_size=64, buffer_size=64))
    ppo.store.add(batch.clone())
    rows = ppo.store.take()
    assert len(rows.end_rows) == 8 + 1  # the 8 horizon cuts and the one MaxStep end
    with torch.no_grad():
        _, advantage, target = ppo.estimate(rows)
    reference = GAE(gamma=0.9, lmbda=0.95, value_network=value_operator(network))
    expected = add_flat_action(batch.exclude(*keys.METADATA))
    with torch.no_grad():
        reference(expected)
    assert torch.allclose(advantage, expected["advantage"].squeeze(-1), atol=1e-5)
    assert torch.allclose(target, expected["value_target"].squeeze(-1), atol=1e-5)


def test_cameras_stay_uint8_and_observations_are_kept_once():
    spec = BehaviorSpec([IMAGE], ActionSpec(0, (3,)))
    store = TrajectoryStore(64)
    pixels = segment(spec, 2, 16)
    pixels[keys.OBS, "camera"] = torch.randint(0, 256, (32, *IMAGE.shape), dtype=torch.uint8)
    pixels[keys.NEXT, keys.OBS, "camera"] = torch.zeros(32, *IMAGE.shape, dtype=torch.uint8)
    store.add(pixels)
    store.add(pixels)
    camera, ends = store.columns["obs/camera"], store.ends["obs/camera"]
    assert camera.dtype == ends.dtype == torch.uint8
    # room for the 64 steps asked and a few segments past them; 4 truncated ends kept
    assert len(camera) == 64 + 64 and len(ends) == 64
    rows = store.take()
    assert torch.equal(rows.obs["camera"], torch.cat([pixels[keys.OBS, "camera"]] * 2))
    assert rows.end_rows.tolist() == [15, 31, 47, 63]
    assert len(rows.end_obs["camera"]) == 4


def test_a_segment_past_the_capacity_grows_the_store():
    spec = vector_spec(branches=(3,))
    store = TrajectoryStore(10)
    parts = [segment(spec, 2, 8, seed=seed) for seed in range(3)]
    for part in parts:
        store.add(part)
    rows = store.take()
    assert len(rows) == 48 and rows.end_rows.tolist() == [7, 15, 23, 31, 39, 47]
    expected = torch.cat([part[keys.OBS, "vector"] for part in parts])
    assert torch.equal(rows.obs["vector"], expected)


def test_a_buffer_that_cannot_fit_is_one_line_naming_the_behavior_and_buffer_size():
    """Refused before it is allocated, as a plain MemoryError, which the driver prints as
    the learner's one line (and keeps the run's checkpoint)."""
    big = ObservationSpec((4096,), (DimensionProperty.NONE,), Obs.DEFAULT, "vector")
    spec = BehaviorSpec([big], ActionSpec(2, ()))
    config = parse_config({"behaviors": {"Big": {"hyperparameters": {"buffer_size": 10**8}}}})
    learner = CentralLearner(config)
    with pytest.raises(MemoryError) as raised:
        learner.submit([segment(spec, 1, 4, behavior="Big?team=0")])
    message = str(raised.value)
    assert "\n" not in message
    assert message.startswith("behavior Big: buffer_size 100000000 needs about 1")
    assert "learner's cpu has" in message and "lower buffer_size" in message
