"""Per-episode sums of the learner's own rewards (``learners/reward_signals/episode_sums.py``), as
ML-Agents reports ``Policy/<Signal> Reward``: one figure per finished episode, however many
updates and pieces it spans."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from batches import keys
from learners.host.learner import make_algorithm
from learners.networks.policies import ActorCritic
from learners.reward_signals.episode_sums import EpisodeSums
from learners.trainer_config.parse import parse_config
from testkit.segments import segment, vector_spec


def rows(agents: list[int], ended: list[bool], *streams: list[float]):
    return (
        torch.tensor(agents, dtype=torch.int64),
        torch.tensor(ended),
        [torch.tensor(s, dtype=torch.float32) for s in streams],
    )


def test_episodes_are_summed_per_agent_across_pieces_and_updates():
    sums = EpisodeSums(streams=2)
    # agent 1: an episode of 3 steps, then the start of the next; agent 2 only begins
    first = sums.finished(
        *rows([1, 1, 1, 2, 2, 1], [0, 0, 1, 0, 0, 0], [1, 2, 3, 10, 20, 4], [0, 0, 1, 0, 0, 0])
    )
    np.testing.assert_allclose(first, [[6, 1]])
    # agent 2 ends (30 + 40 more), agent 1 ends after 5 more, and a short one of 7 follows
    second = sums.finished(*rows([2, 1, 1], [1, 1, 1], [40, 5, 7], [1, 0, 0]))
    assert sorted(map(tuple, second.tolist())) == [(7.0, 0.0), (9.0, 0.0), (70.0, 1.0)]
    assert sums.finished(*rows([3], [0], [1.0], [0.0])).shape == (0, 2)  # none ended


def test_only_so_many_unfinished_episodes_are_kept():
    sums = EpisodeSums(streams=1, carried=2)
    sums.finished(*rows([1, 2, 3], [0, 0, 0], [1, 1, 1]))  # agent 1 is dropped (it left)
    np.testing.assert_allclose(sums.finished(*rows([1, 3], [1, 1], [5, 5])), [[5], [6]])


def curiosity_ppo():
    config = parse_config(
        {
            "behaviors": {
                "B": {
                    "trainer_type": "ppo",
                    "hyperparameters": {"batch_size": 8, "buffer_size": 16},
                    "reward_signals": {"curiosity": {"strength": 0.5}},
                }
            }
        }
    )
    settings = config.for_behavior("B")
    spec = vector_spec(4, branches=(2,))
    return make_algorithm(ActorCritic(spec, settings.network_settings), settings), spec


@pytest.mark.parametrize("cut", [True, False], ids=["cut", "interrupted"])
def test_ppo_reports_the_curiosity_of_each_episode_over_two_updates(cut):
    """After a first update (curiosity rewards nothing before its networks trained once),
    one agent's episode of 40 steps over two updates: its first row ends at the horizon
    (``cut``: the episode goes on) or by an interruption (it ended there)."""
    ppo, spec = curiosity_ppo()
    rewards = []

    def update(piece, agent: int):
        piece[keys.AGENT_ID] = torch.full((len(piece),), agent, dtype=torch.int64)
        ppo.add(piece, torch.zeros(len(piece), dtype=torch.int64))
        report = ppo.update(progress=0.0)
        rewards.append(ppo.signals._rewards[0].clone())  # this update's, strength-weighted
        return report

    update(segment(spec, rows=1, steps=20, seed=0), agent=9)
    first = segment(spec, rows=1, steps=20, seed=1)
    first[keys.NEXT, keys.CUT] = first[keys.NEXT, keys.TRUNCATED].clone() & cut
    report = update(first, agent=3)
    assert ("Policy/Curiosity Reward" in report) != cut  # an episode ended, or none did
    second = segment(spec, rows=1, steps=20, seed=2)
    second[keys.NEXT, keys.CUT] = torch.zeros_like(second[keys.NEXT, keys.DONE])  # it ends
    report = update(second, agent=3)
    assert float(rewards[1].sum()) > 0  # the first piece's curiosity counts (or not)
    expected = float(rewards[2].sum()) + (float(rewards[1].sum()) if cut else 0.0)
    assert report["Policy/Curiosity Reward"] == pytest.approx(expected, rel=1e-5)
