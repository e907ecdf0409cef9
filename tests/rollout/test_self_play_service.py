"""Self-play across Ray workers on unitysim SoccerTwos: the learner alone decides which team
learns and what the other plays, so a worker killed mid-game, and its replacement joining,
change nothing of it. Steps are classified by the weights version that acted them; the
learning team changes every ``team_change`` of the brain's own steps, whatever the
workers did."""

from __future__ import annotations

import os
import signal
from itertools import pairwise

import pytest

from learners.acting.factory import policy_factory
from learners.host.remote import learner_actor
from learners.trainer_config.parse import parse_config
from rollout.environment.ports import PortAllocator
from rollout.environment.unity import UnityConfig
from rollout.serving.service import RolloutService
from tests.helpers import wait_gone
from tests.rollout.workers import PORTS, service_config
from tests.waiting import poll_until

pytestmark = pytest.mark.integration

TEAM_CHANGE = 1500
CONFIG = {
    "behaviors": {
        "SoccerTwos": {
            "trainer_type": "ppo",
            "hyperparameters": {"batch_size": 128, "buffer_size": 512, "num_epoch": 1},
            "network_settings": {"hidden_units": 16, "num_layers": 1},
            "time_horizon": 16,
            "self_play": {
                "save_steps": 600,
                "team_change": TEAM_CHANGE,
                "swap_steps": 400,
                "window": 3,
            },
        }
    }
}


def test_a_worker_killed_mid_game_changes_nothing_of_who_learns(ray_session, registry):
    config = parse_config(CONFIG)
    learner = learner_actor(config)
    unity = UnityConfig("unitysim:SoccerTwos", additional_args=("--no-parent-watch",))
    service = RolloutService(service_config(unity, registry), policy_factory(config), learner)
    try:
        service.start()
        service.run(agent_steps=2000)
        victim = ray_session.get(service.workers[0].identity.remote())
        os.kill(victim["pid"], signal.SIGKILL)  # in the middle of its games
        assert wait_gone(victim["player_pid"])

        def brain_steps() -> int:
            return sum(ray_session.get(learner.progress.remote())["steps"].values())

        service.run(  # until the replacement has played too
            until=lambda m: m.worker_restarts >= 1 and brain_steps() > 2 * TEAM_CHANGE + 600,
            seconds=240,
        )
        metrics = service.metrics
        state = ray_session.get(learner.state_dict.remote())
    finally:
        service.stop()
        ray_session.kill(learner)
        # a replacement's player launched as the run stopped ends with its worker, soon
        allocator = PortAllocator(PORTS, registry)
        poll_until(lambda: not allocator.leases(), 60)
    assert metrics.worker_restarts >= 1
    (brain,) = state["behaviors"].values()
    self_play = state["self_play"]
    changes = [(int(v), int(t)) for v, t in self_play["changes"]]
    teams = [t for _, t in changes]
    # the learning team changed with the brain's own steps: once past each TEAM_CHANGE
    assert 2 <= len(changes) - 1 <= brain["steps"] // TEAM_CHANGE, (changes, brain["steps"])
    assert all(a != b for a, b in pairwise(teams)), teams  # taking turns
    assert [v for v, _ in changes] == sorted(v for v, _ in changes)
    ghost = self_play["ghosts"]["SoccerTwos"]
    assert ghost["ghost_steps"] > 0 and len(ghost["snapshots"]) >= 2
    assert set(state["behavior_keys"]) == {"SoccerTwos?team=0", "SoccerTwos?team=1"}
