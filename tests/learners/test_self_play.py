"""Self-play in the central learner, without Ray, against ML-Agents' ghost trainer's rules:
one brain for both teams of a symmetric game, the learning team's steps only, opponents'
snapshots as their weights, team changes and swaps as new versions, steps classified by
the version that acted, ELO from finished games, an asymmetric game's two brains, and
checkpoints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from batches import keys
from batches.contracts import Snapshot
from learners.algorithms.self_play import learning_steps
from learners.host.learner import CentralLearner
from learners.trainer_config.parse import ConfigError, parse_config
from learners.trainer_config.settings import SelfPlaySettings
from testkit.segments import segment, vector_spec

SPEC = vector_spec(4, branches=(3,))
SELF_PLAY = {
    "save_steps": 40,
    "team_change": 100,
    "swap_steps": 30,
    "window": 3,
    "play_against_latest_model_ratio": 0.0,
}


def config(names=("Soccer",), **self_play):
    section = {
        "trainer_type": "ppo",
        "hyperparameters": {"batch_size": 8, "buffer_size": 16, "learning_rate": 0.01},
        "network_settings": {"hidden_units": 8, "num_layers": 1},
        "self_play": {**SELF_PLAY, **self_play},
    }
    return parse_config({"behaviors": {name: section for name in names}})


def played(behavior: str, version: int, steps: int = 10, seed: int = 0, reward: float = 0.0):
    batch = segment(SPEC, 1, steps, behavior=behavior, seed=seed)
    batch[keys.POLICY_VERSION] = torch.full((steps,), version)
    batch[keys.NEXT, keys.REWARD] = torch.zeros(steps, 1)
    if reward:  # the game ends, won or lost
        batch[keys.NEXT, keys.TRUNCATED][-1] = False
        batch[keys.NEXT, keys.TERMINATED][-1] = True
        batch[keys.NEXT, keys.REWARD][-1] = reward
    return batch


def same(a: dict, b: dict) -> bool:
    return all(np.array_equal(a[k], b[k]) for k in a)


def test_the_section_reads_as_ml_agents_reads_it():
    settings = config().behaviors["Soccer"].self_play
    assert settings == SelfPlaySettings(40, 100, 30, 3, 0.0, 1200.0)
    default = parse_config({"behaviors": {"S": {"self_play": {"save_steps": 7}}}})
    assert default.behaviors["S"].self_play.team_change == 35  # 5 x save_steps
    with pytest.raises(ConfigError, match=r"^behaviors.S.self_play.windw: unknown key"):
        parse_config({"behaviors": {"S": {"self_play": {"windw": 3}}}})
    with pytest.raises(ConfigError, match=r"play_against_latest_model_ratio: expected a number"):
        parse_config({"behaviors": {"S": {"self_play": {"play_against_latest_model_ratio": 2}}}})


def test_both_teams_share_one_brain_and_only_the_learning_team_trains():
    learner = CentralLearner(config())
    learner.submit([played("Soccer?team=0", 0), played("Soccer?team=1", 0)])
    assert list(learner.behaviors) == ["Soccer?team=0"]  # one network for both teams
    (state,) = learner.behaviors.values()
    assert state.steps == 10  # team 0 learns first; team 1's steps are ghost steps
    assert learner.self_play.ghosts["Soccer"].ghost_steps == 10
    version, weights = learner.weights()
    assert set(weights) == {"Soccer?team=0", "Soccer?team=1"}
    learner.submit([played("Soccer?team=0", version, seed=1)])  # 20 > buffer_size: update
    version, weights = learner.weights()
    assert state.updates and version >= state.updates[-1]
    current = {k: v.detach().numpy() for k, v in state.network.state_dict().items()}
    assert same(weights["Soccer?team=0"], current)
    opponent = weights["Soccer?team=1"]  # the initial policy: a snapshot, under its key
    assert isinstance(opponent, Snapshot) and not same(opponent.state, current)
    assert opponent.key == learner.self_play.ghosts["Soccer"].snapshot_keys[0]
    assert opponent.key in learner.self_play.snapshot_keys()


def test_team_changes_and_swaps_are_versions_and_steps_count_by_the_version_that_acted():
    learner = CentralLearner(config())
    (state,) = [learner._behavior("Soccer?team=0", learner_spec())]
    learner._behavior("Soccer?team=1", learner_spec())
    before = learner.version
    for seed in range(11):  # 110 learning steps: past team_change
        learner.submit([played("Soccer?team=0", learner.version, seed=seed)])
    assert learner.self_play.learning_team == 1
    changed_at = learner.self_play.changes[-1][0]
    assert changed_at > before and learner.version >= changed_at
    version, weights = learner.weights()
    current = {k: v.detach().numpy() for k, v in state.network.state_dict().items()}
    assert same(weights["Soccer?team=1"], current)  # team 1 now plays the learning policy
    steps = state.steps
    # a worker still acting with the old weights: team 1's steps were a snapshot's, ghost
    learner.submit([played("Soccer?team=1", changed_at - 1, seed=20)])
    assert state.steps == steps
    learner.submit([played("Soccer?team=1", version, seed=21)])  # with the new ones: learned
    assert state.steps == steps + 10
    # ghost steps of team 0 past swap_steps: a new opponent, a new version
    version = learner.version
    for seed in range(4):
        learner.submit([played("Soccer?team=0", version, seed=30 + seed)])
    assert learner.version > version


def test_a_game_won_against_a_snapshot_moves_the_elo_as_ml_agents():
    learner = CentralLearner(config())
    learner._behavior("Soccer?team=0", learner_spec())
    learner._behavior("Soccer?team=1", learner_spec())
    ghost = learner.self_play.ghosts["Soccer"]
    ghost.opponent = 0  # playing the initial snapshot, rated 1200 as the current
    learner.submit([played("Soccer?team=0", 0, reward=1.0)])
    assert ghost.elo == pytest.approx(1200.5)  # result 1, expected 0.5
    assert ghost.elos[0] == pytest.approx(1199.5)
    learner.submit([played("Soccer?team=0", 0, seed=2, reward=-1.0)])  # a loss
    expected = 1 / (1 + 10 ** ((1199.5 - 1200.5) / 400))
    assert ghost.elo == pytest.approx(1200.5 - expected)
    learner.submit([played("Soccer?team=1", 0, seed=3, reward=1.0)])  # the ghost's win: no ELO
    assert ghost.elo == pytest.approx(1200.5 - expected)


def test_an_asymmetric_game_has_a_brain_per_side_and_the_other_side_plays_a_snapshot():
    learner = CentralLearner(config(("Striker", "Goalie")))
    learner.submit([played("Striker?team=0", 0), played("Goalie?team=1", 0)])
    striker, goalie = learner.behaviors["Striker?team=0"], learner.behaviors["Goalie?team=1"]
    assert (striker.steps, goalie.steps) == (10, 0)
    assert learner.self_play.ghosts["Goalie"].ghost_steps == 10
    for seed in range(11):
        learner.submit([played("Striker?team=0", learner.version, seed=seed)])
    assert learner.self_play.learning_team == 1  # now the goalie learns
    learner.submit([played("Goalie?team=1", learner.version, seed=40)])
    assert goalie.steps == 10


def test_the_learning_part_of_a_row_ends_truncated_where_the_team_stopped_learning():
    batch = segment(SPEC, 1, 6)
    keep = torch.tensor([True, True, True, False, False, False])
    part = learning_steps(batch, keep)
    assert len(part) == 3
    assert part[keys.NEXT, keys.TRUNCATED][-1] and part[keys.NEXT, keys.DONE][-1]
    torch.testing.assert_close(
        part[keys.NEXT, keys.OBS, "vector"], batch[keys.NEXT, keys.OBS, "vector"][:3]
    )


def test_a_checkpoint_brings_the_snapshots_elo_and_learning_team_back(tmp_path):
    learner = CentralLearner(config())
    learner.submit([played("Soccer?team=0", 0, reward=1.0), played("Soccer?team=1", 0)])
    for seed in range(11):
        learner.submit([played("Soccer?team=0", learner.version, seed=seed)])
    torch.save(learner.state_dict(), tmp_path / "c.pt")
    state = torch.load(tmp_path / "c.pt", weights_only=True)  # as checkpoints are read
    again = CentralLearner(config())
    again.load_state_dict(state)
    mine, theirs = learner.self_play, again.self_play
    assert (theirs.learning_team, theirs.changes) == (mine.learning_team, mine.changes)
    ghost, loaded = mine.ghosts["Soccer"], theirs.ghosts["Soccer"]
    assert loaded.elos == ghost.elos and len(loaded.snapshots) == len(ghost.snapshots)
    assert all(same(a, b) for a, b in zip(loaded.snapshots, ghost.snapshots, strict=True))
    assert again.weights()[1].keys() == learner.weights()[1].keys()


def learner_spec() -> dict:
    from batches.specs import spec_to_dict

    return spec_to_dict(SPEC)


def test_a_side_that_has_its_max_steps_hands_over_to_the_other():
    """mlagents-learn would wait forever for a goalie that never gets its turn."""
    learner = CentralLearner(config(("Striker", "Goalie")), max_steps=30)
    # the first team seen learns first; the goalie a ghost meanwhile, no steps of its own
    learner.submit([played("Striker?team=0", 0), played("Goalie?team=1", 0, seed=9)])
    for seed in range(1, 4):
        learner.submit([played("Striker?team=0", learner.version, seed=seed)])
    assert learner.self_play.learning_team == 1
    for seed in range(4):
        learner.submit([played("Goalie?team=1", learner.version, seed=10 + seed)])
    assert learner.progress()["done"]


def test_teams_the_workers_met_join_before_their_first_rows():
    """A goalie's first row may take its time_horizon to come: the workers' specs say it
    plays, and the striker hands over when it has its steps."""
    learner = CentralLearner(config(("Striker", "Goalie")), max_steps=30)
    learner.meet({"Striker?team=0": learner_spec(), "Goalie?team=1": learner_spec()})
    assert learner.self_play.team_ghost == {0: "Striker", 1: "Goalie"}
    for seed in range(4):
        learner.submit([played("Striker?team=0", learner.version, seed=seed)])
    assert learner.self_play.learning_team == 1  # no goalie row has arrived yet
    assert set(learner.weights()[1]) == {"Striker?team=0", "Goalie?team=1"}


def test_initialized_from_another_run_the_opponent_plays_its_networks_not_the_factorys():
    """``--initialize-from``: the ghost's first snapshot, which the other team plays, is the
    loaded policy (as ML-Agents' ghost snapshots after loading), sent with a version of its
    own."""
    source = CentralLearner(config(), seed=1)
    source.submit([played("Soccer?team=0", 0, seed=n) for n in range(2)])  # an update
    fresh = CentralLearner(config(), seed=2)
    fresh.initialize(source.state_dict())
    fresh._behavior("Soccer?team=1", learner_spec())  # the other team appears afterwards
    loaded = {
        k: v.detach().numpy()
        for k, v in source.behaviors["Soccer?team=0"].network.state_dict().items()
    }
    version, weights = fresh.weights()
    assert version == 1 and same(weights["Soccer?team=0"], loaded)
    opponent = weights["Soccer?team=1"]
    assert isinstance(opponent, Snapshot) and same(opponent.state, loaded)
    ghost = fresh.self_play.ghosts["Soccer"]
    assert opponent.key == ghost.snapshot_keys[0] and len(ghost.snapshots) == 1
