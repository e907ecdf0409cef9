"""Self-play opponents travel as snapshots: a worker takes each one's state once, however
many weights versions of the learning policy carry it, and the learner's Ray actor puts
each once. unitysim SoccerTwos, its two teams: team 0 learns, team 1 plays a snapshot."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import ray
from mlagents_envs.base_env import BehaviorSpec

from batches.contracts import Snapshot
from batches.specs import spec_to_dict
from learners.acting.factory import PolicyFactory, policy_factory
from learners.host.remote import learner_actor
from learners.trainer_config.parse import parse_config
from rollout.collecting.collector import SNAPSHOTS_KEPT, Collector
from rollout.environment.unity import UnityConfig
from testkit.segments import segment, vector_spec
from tests.helpers import leak_checked_allocator

pytestmark = pytest.mark.integration

CONFIG = {
    "behaviors": {
        "SoccerTwos": {
            "trainer_type": "ppo",
            "hyperparameters": {"batch_size": 16, "buffer_size": 32, "num_epoch": 1},
            "network_settings": {"hidden_units": 8, "num_layers": 1},
            "self_play": {"save_steps": 1000, "team_change": 5000, "swap_steps": 1000},
        }
    }
}


class Recording:
    """An actor that records the states it was given (an ``Actor``: it acts for real)."""

    def __init__(self, factory: PolicyFactory, behavior: str, spec: BehaviorSpec) -> None:
        self.actor = factory(behavior, spec)
        self.loads: list[dict[str, np.ndarray]] = []

    def act(self, obs: dict[str, np.ndarray], mask: np.ndarray | None = None) -> Any:
        return self.actor.act(obs, mask)

    def to_unity(self, continuous: np.ndarray) -> np.ndarray:
        return self.actor.to_unity(continuous)

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.loads.append(state)
        self.actor.load_state_dict(state)


def scaled(state: dict[str, np.ndarray], factor: float) -> dict[str, np.ndarray]:
    return {k: v * factor for k, v in state.items()}


def test_a_worker_takes_each_snapshot_once_and_loads_it_only_when_it_changes(tmp_path):
    factory = policy_factory(parse_config(CONFIG))
    actors: dict[str, Recording] = {}

    def recording(behavior: str, spec: BehaviorSpec) -> Recording:
        actors[behavior] = Recording(factory, behavior, spec)
        return actors[behavior]

    with leak_checked_allocator(tmp_path, 24300, 24319) as allocator:
        collector = Collector(UnityConfig("unitysim:SoccerTwos"), recording, 16, 0, allocator)
        try:
            collector.start()
            collector.collect(min_steps=64)  # both teams met: their actors exist
            learning, opponent = actors["SoccerTwos?team=0"], actors["SoccerTwos?team=1"]
            spec = collector.builders["SoccerTwos?team=0"].spec
            base = factory.initial_weights("SoccerTwos?team=0", spec)
            first = Snapshot("first", scaled(base, 0.5))
            collector.load_weights(1, {"SoccerTwos?team=0": base, "SoccerTwos?team=1": first})
            for version in range(2, 6):  # new learning weights, the same opponent
                held = Snapshot("first", None)  # its state need not come again
                learning_state = scaled(base, 1 + version / 10)
                weights = {"SoccerTwos?team=0": learning_state, "SoccerTwos?team=1": held}
                collector.load_weights(version, weights)
                collector.collect(min_steps=32)
            assert collector.metrics.snapshots_received == 1
            assert len(learning.loads) == 5 and len(opponent.loads) == 1
            assert opponent.loads[0] is first.state
            np.testing.assert_array_equal(
                learning.loads[-1]["trunk.0.weight"], learning_state["trunk.0.weight"]
            )
            # a swap to a new snapshot: taken in; then back to the first, from the cache
            second = Snapshot("second", scaled(base, 0.25))
            collector.load_weights(6, {"SoccerTwos?team=0": base, "SoccerTwos?team=1": second})
            collector.load_weights(7, {"SoccerTwos?team=0": base, "SoccerTwos?team=1": held})
            assert collector.metrics.snapshots_received == 2
            assert [s is first.state for s in opponent.loads] == [True, False, True]
            assert opponent.loads[1] is second.state
            # a team change: team 1 learns with plain weights, team 0 plays the second
            swapped = {"SoccerTwos?team=0": Snapshot("second", None), "SoccerTwos?team=1": base}
            collector.load_weights(8, swapped)
            assert learning.loads[-1] is second.state and opponent.loads[-1] is base
            assert collector.metrics.snapshots_received == 2
            collector.collect(min_steps=32)  # both act with them
            for number in range(SNAPSHOTS_KEPT - 1):  # bounded: the least recently used goes
                fresh = Snapshot(f"s{number}", base)
                collector.load_weights(9 + number, {"SoccerTwos?team=1": fresh})
            assert not collector.holds("first") and collector.holds("second")
        finally:
            collector.close()


def test_the_learner_actor_puts_each_snapshot_once(ray_session):
    config = parse_config(CONFIG)
    learner = learner_actor(config)
    try:
        spec = spec_to_dict(vector_spec(continuous=2))
        ray.get(learner.meet.remote({f"SoccerTwos?team={t}": spec for t in (0, 1)}))
        published = []
        for seed in range(3):  # each fills a buffer: an update, a new version
            version, weights = ray.get(learner.weights.remote())
            published.append((version, weights))
            rows = segment(vector_spec(continuous=2), 2, 20, "SoccerTwos?team=0", seed)
            ray.get(learner.submit.remote([rows]))
        versions = [v for v, _ in published]
        assert versions == sorted(set(versions)), versions  # every round a new version
        opponents = [w["SoccerTwos?team=1"] for _, w in published]
        assert all(isinstance(o, Snapshot) for o in opponents)
        assert len({o.key for o in opponents}) == 1  # no swap: the same opponent
        refs = [o.state for o in opponents]
        assert all(isinstance(r, ray.ObjectRef) for r in refs)
        assert len({r.hex() for r in refs}) == 1  # put once, referenced by every version
        state = ray.get(refs[0])
        assert set(state) == set(published[-1][1]["SoccerTwos?team=0"])
    finally:
        ray.kill(learner)
