"""``UnityCollector`` on real Ray workers and unitysim players: batches under torchrl's
names and of exactly ``frames_per_batch`` steps, the user's weights reaching every worker,
nothing left running after ``shutdown``; and docs/examples/torchrl_ppo.py (torchrl's
``ClipPPOLoss``, GAE and a replay buffer) trained on a step budget."""

from __future__ import annotations

import gc
import importlib.util
from multiprocessing import resource_tracker
from pathlib import Path

import pytest
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from rollout.environment.ports import PortAllocator, PortRange
from tests.helpers import wait_gone
from torchrl_adapters import UnityCollector

pytestmark = pytest.mark.integration

PORTS = PortRange(24400, 24449)
EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "torchrl_ppo.py"


def example():
    spec = importlib.util.spec_from_file_location("torchrl_ppo", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def registry(tmp_path):
    directory = str(tmp_path / "ports")
    yield directory
    assert PortAllocator(PORTS, directory).leases() == {}, "a port is still leased"


def options(registry: str) -> dict:
    return {"num_workers": 2, "worker_cpus": 0.5, "port_range": PORTS, "registry_dir": registry}


def test_batches_are_exact_in_torchrls_names_and_new_weights_reach_the_workers(
    ray_session, registry
):
    actor, _ = example().make_actor_critic(8, 2)
    collector = UnityCollector(
        "unitysim:3DBall", actor, 300, 2100, behavior="3DBall", horizon=32, **options(registry)
    )
    batches, players = [], []
    try:
        for batch in collector:
            batches.append(batch)
            if len(batches) == 2:  # new weights: every action's mean at tanh(5), near 1
                players = [
                    ray_session.get(w.identity.remote())["player_pid"]
                    for w in collector._service.workers
                ]
                with torch.no_grad():
                    for parameter in actor.parameters():
                        parameter.zero_()
                    last_layer = [m for m in actor.modules() if isinstance(m, nn.Linear)][-1]
                    last_layer.bias[:2] = 5.0  # the two means (the scales follow)
                collector.update_policy_weights_()
    finally:
        collector.shutdown()
    assert [b.batch_size for b in batches] == [torch.Size([300])] * 7
    assert collector.frames == 2100
    first = batches[0]
    assert first["observation"].shape == (300, 8) and first["action"].shape == (300, 2)
    assert first["next", "observation"].shape == (300, 8)
    assert first["action_log_prob"].shape == (300,) and first["next", "done"][-1].item()
    # rows are consecutive steps of one agent: within a row, the next observation is the
    # following step's observation
    inside = ~first["next", "done"][:-1, 0]
    nxt, obs = first["next", "observation"][:-1], first["observation"][1:]
    torch.testing.assert_close(nxt[inside], obs[inside])
    # after the update, the steps acted by the new weights carry its version and its law
    last = torch.cat(batches[2:])  # after the update (steps in flight then: the old weights)
    new = last["policy_version"] == last["policy_version"].max()
    assert int(last["policy_version"].max()) > int(first["policy_version"].max())
    assert first["action"].mean().abs() < 0.3  # the initial policy: centred
    assert new.sum() > 100 and last["action"][new].mean() > 0.9
    assert all(wait_gone(pid) for pid in players)


def test_the_torchrl_ppo_example_trains_on_a_step_budget(ray_session, registry):
    history = example().train(
        total_frames=3 * 1024, frames_per_batch=1024, minibatch=256, epochs=2, **options(registry)
    )
    # torchrl's storages keep counters in multiprocessing values, whose semaphores start
    # the interpreter's resource tracker: stopped here, the buffer being gone
    gc.collect()
    resource_tracker._resource_tracker._stop()
    assert len(history) == 3
    assert all(torch.isfinite(torch.tensor(h["loss"])) for h in history)
    assert history[-1]["policy_version"] >= 1  # acted by weights the loop trained


class RandomBranches(TensorDictModuleBase):
    """A policy of three branches of three choices: what acts matters not here."""

    in_keys, out_keys = ["observation"], ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict["action"] = torch.randint(0, 3, (tensordict.batch_size[0], 3))
        return tensordict


def test_every_behavior_comes_as_its_own_entry_with_a_policy_each(ray_session, registry):
    """StrikersVsGoalie: two behaviors, a policy each by name; without ``behavior`` a batch
    is keyed by behavior id, each entry flat under torchrl's names."""
    policies = {"Striker": RandomBranches(), "Goalie": RandomBranches()}
    collector = UnityCollector(
        "unitysim:StrikersVsGoalie", policies, 200, 400, horizon=32, **options(registry)
    )
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert batches and collector.frames >= 400  # a batch holds whatever was taken: >= 200
    entries = [(name, batch[name]) for batch in batches for name in batch.keys()]  # noqa: SIM118
    assert {name for name, _ in entries} == {"Striker?team=0", "Goalie?team=1"}
    assert all(sum(batch[n].numel() for n in batch.keys()) >= 200 for batch in batches)  # noqa: SIM118
    for name, entry in entries:
        team = 0 if name == "Striker?team=0" else 1
        assert entry["action"].shape[1:] == (3,) and entry["team"].eq(team).all()
        assert entry["next", "done"][-1].item()
        if team == 0:  # two sensors: by name
            assert set(entry["observation"].keys()) == {
                "StackingSensor_size3_BlueRayPerceptionSensor",
                "StackingSensor_size3_BlueRayPerceptionSensorReverse",
            }
        else:
            assert entry["observation"].shape[1:] == (738,)  # one sensor: its tensor
