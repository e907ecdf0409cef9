"""SAC with ``network_settings.memory``: sequences in the replay buffer with the memories the
workers stored, the actor from them, the Qs' LSTMs from zeros, checkpoints, and SAC learning
what only memory solves."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from batches import keys
from learners.algorithms.recurrent_sac import VALID, RecurrentSAC
from learners.algorithms.sac import SAC
from learners.host.learner import make_algorithm
from learners.networks.policies import ActorCritic
from learners.trainer_config.parse import defaults, load_config
from learners.trainer_config.settings import MemorySettings, NetworkSettings, RewardSignalSettings
from testkit.segments import segment, vector_spec
from tests.learners.test_memory import CUE_STEPS, learn_recall

ANCHORS = Path(__file__).resolve().parents[3] / "shared" / "anchors" / "mlagents-configs"


def build(spec, memory: MemorySettings | None, **hyper) -> SAC:
    base = defaults("sac")
    network = NetworkSettings(
        hidden_units=16, memory=memory, tanh_squash=True, conditional_sigma=True
    )
    h = replace(base.hyperparameters, **{"batch_size": 8, "buffer_init_steps": 0, **hyper})
    settings = replace(base, hyperparameters=h, network_settings=network)
    torch.manual_seed(0)
    return make_algorithm(ActorCritic(spec, network), settings)


def pieces(spec, memory_size: int):
    """A packed segment of two pieces (5 and 3 steps), each step with a distinct memory."""
    batch = segment(spec, 1, 8)
    batch[keys.NEXT, keys.DONE][4] = True
    batch[keys.MEMORY] = torch.arange(8.0).unsqueeze(-1).expand(8, memory_size).clone()
    return batch


@pytest.mark.skipif(not ANCHORS.is_dir(), reason="ML-Agents' configs are not beside the repo")
def test_mlagents_sac_hallway_config_runs_with_memory():
    config = load_config(ANCHORS / "sac" / "Hallway.yaml")
    assert config.unsupported == ()
    assert config.behaviors["Hallway"].network_settings.memory == MemorySettings(128, 64)


@pytest.mark.parametrize("actions", [(2, ()), (0, (3,))], ids=["continuous", "discrete"])
def test_the_buffer_holds_padded_sequences_with_their_memories(actions):
    spec = vector_spec(4, *actions)
    sac = build(spec, MemorySettings(8, 2))
    assert isinstance(sac, RecurrentSAC)
    sac.add(pieces(spec, 8), torch.zeros(8, dtype=torch.int64))
    stored = sac.buffer.storage[: len(sac.buffer)]
    assert stored.batch_size == (5, 2)  # pieces of 5 and 3 in sequences of 2
    assert stored[VALID].tolist() == [[1, 1], [1, 1], [1, 0], [1, 1], [1, 0]]
    assert stored[keys.MEMORY][:, :, 0].tolist() == [[0, 1], [2, 3], [4, 4], [5, 6], [7, 7]]
    assert sac.stored_steps() == 10 and sac.buffer.sample().batch_size == (4, 2)


def test_the_actor_reads_the_stored_memory_and_the_qs_start_from_zeros():
    """Another memory at a sequence's start moves the policy, not the Qs; a padded
    sequence's real steps get what the networks give that piece alone."""
    spec = vector_spec(4, 2, ())
    sac = build(spec, MemorySettings(8, 4))
    assert isinstance(sac, RecurrentSAC)
    sac.add(pieces(spec, 8), torch.zeros(8, dtype=torch.int64))
    batch = sac.buffer.storage[: len(sac.buffer)]  # sequences: 4, 1 (+3 padding), 3 (+1)

    def passes(sequences):
        inputs = sac.inputs(sequences)
        flat = sequences[sequences[VALID]]
        q = sac.q_values(sac.q, inputs, [flat["continuous_action"]])
        return sac.policy_params(inputs)[0], q

    with torch.no_grad():
        loc, q = passes(batch)
        other = batch.clone()
        other[keys.MEMORY] = other[keys.MEMORY] + 1.0
        other_loc, other_q = passes(other)
        assert not torch.allclose(loc, other_loc)
        torch.testing.assert_close(q, other_q)
        # the last piece (3 real steps of 4) as a sequence of its own, without padding
        alone = batch[2:3, :3]
        alone[VALID] = torch.ones(1, 3, dtype=torch.bool)
        alone_loc, alone_q = passes(alone)
        torch.testing.assert_close(alone_loc, loc[-3:])
        torch.testing.assert_close(alone_q, q[:, -3:])


@pytest.mark.parametrize("actions", [(2, ()), (0, (3,))], ids=["continuous", "discrete"])
def test_a_gradient_step_runs_and_the_state_round_trips(actions):
    spec = vector_spec(4, *actions)
    sac = build(spec, MemorySettings(8, 2), steps_per_update=1.0)
    for _ in range(2):  # the first fills the buffer to batch_size
        sac.add(pieces(spec, 8), torch.zeros(8, dtype=torch.int64))
    assert sac.ready()
    report = sac.update(0.0)
    assert report["Policy/Gradient Steps"] > 0 and np.isfinite(report["Losses/Q1 Loss"])
    fresh = build(spec, MemorySettings(8, 2))
    fresh.load_state_dict(sac.state_dict())
    for mine, theirs in zip(fresh.q.parameters(), sac.q.parameters(), strict=True):
        torch.testing.assert_close(mine, theirs)
    assert any("lstm" in name for name, _ in fresh.q.named_parameters())


def test_sac_with_memory_learns_to_recall_a_cue():
    """Only the first step shows the cue; the last asks for it (tests/learners/test_memory.py).
    SAC with memory gets near every choice right; without, it stays near half."""
    spec = vector_spec(3, 0, (2,))
    hyper = {"batch_size": 64, "steps_per_update": 4.0, "learning_rate": 3e-3}
    sac = build(spec, MemorySettings(32, CUE_STEPS), **hyper)
    scores = learn_recall(sac.network, sac, 15)
    assert np.mean(scores[-3:]) > 0.95, scores
    sac = build(spec, None, **hyper)
    scores = learn_recall(sac.network, sac, 10)
    assert np.mean(scores[-5:]) < 0.65, scores


def test_memory_and_a_reward_signal_train_together():
    """Curiosity under a recurrent SAC: its stream in the Qs, its networks trained on the
    sampled sequences' real steps."""
    spec = vector_spec(4, 0, (3,))
    sac = build(spec, MemorySettings(8, 2), steps_per_update=1.0)
    curiosity = RewardSignalSettings("curiosity", network_settings=NetworkSettings(16, 1))
    settings = replace(sac.settings, reward_signals=(curiosity,))
    sac = make_algorithm(sac.network, settings)
    assert isinstance(sac, RecurrentSAC) and sac.streams == 2
    for _ in range(3):
        sac.add(pieces(spec, 8), torch.zeros(8, dtype=torch.int64))
    report = sac.update(0.0)
    assert np.isfinite(report["Losses/Curiosity Forward Loss"])
    assert np.isfinite(report["Losses/Q1 Loss"])
