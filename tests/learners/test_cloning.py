"""``behavioral_cloning``: the section checked, demonstrations paired as ML-Agents pairs
them, the policy pulled to the expert's actions (and the critic left alone), the rate's
linear decay to a stop, and demonstrations that do not fit the behavior refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from demonstrations import Demonstration, DemoStep, expert_steps, write_demo
from learners.host.learner import CentralLearner
from learners.networks.policies import ActorCritic
from learners.reward_signals.cloning import REPORT, BehavioralCloning
from learners.trainer_config.parse import ConfigError, parse_config
from learners.trainer_config.settings import (
    BehavioralCloningSettings,
    Hyperparameters,
    MemorySettings,
    NetworkSettings,
)
from testkit.segments import segment
from tests.demonstrations.samples import CONTINUOUS, DISCRETE, sensor, spec


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"strength": 0.5}, "behavioral_cloning.demo_path: required"),
        ({"demo_path": "x.demo", "steps": -1}, "behavioral_cloning.steps"),
        ({"demo_path": "x.demo", "batch_size": 0}, "behavioral_cloning.batch_size"),
        ({"demo_path": "x.demo", "samples": 10}, "behavioral_cloning.samples: unknown key"),
    ],
)
def test_the_section_is_checked(section: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_config({"behaviors": {"B": {"behavioral_cloning": section}}})


def expert(behavior, count: int, seed: int = 0) -> Demonstration:
    """An expert whose action is a fixed function of what it sees: continuous actions a
    linear map of the first sensor (in [-1, 1]), discrete ones its signs."""
    rng = np.random.default_rng(seed)
    actions = behavior.action_spec
    steps = []
    for i in range(count):
        obs = tuple(rng.normal(size=o.shape).astype(np.float32) for o in behavior.observation_specs)
        first = obs[0]
        steps.append(
            DemoStep(
                observations=obs,
                done=i % 20 == 19,
                continuous=np.tanh(first[: actions.continuous_size] - first[1]),
                discrete=[int(first[b] > 0) for b in range(len(actions.discrete_branches))],
            )
        )
    return Demonstration.of_steps("Expert", "Expert", behavior, steps)


def test_steps_pair_each_record_with_its_own_action_and_drop_the_last(tmp_path) -> None:
    demo = expert(DISCRETE, 7)
    write_demo(tmp_path / "e.demo", demo)
    steps = expert_steps(tmp_path / "e.demo")
    assert len(steps) == 6  # ML-Agents' demo_to_buffer stops before the last record
    for row, step in enumerate(demo.steps[:-1]):
        for sensor_obs, recorded in zip(steps.observations, step.observations, strict=True):
            np.testing.assert_array_equal(sensor_obs[row], recorded)
        np.testing.assert_array_equal(steps.discrete[row], step.discrete)
    assert steps.problem_with(DISCRETE) is None
    assert "do not match" in steps.problem_with(CONTINUOUS)


def cloning(
    tmp_path, behavior, memory: MemorySettings | None = None, **settings
) -> tuple[ActorCritic, BehavioralCloning]:
    write_demo(tmp_path / "e.demo", expert(behavior, 513))
    torch.manual_seed(0)
    network = ActorCritic(behavior, NetworkSettings(hidden_units=32, num_layers=2, memory=memory))
    given = BehavioralCloningSettings(str(tmp_path / "e.demo"), **settings)
    hyper = Hyperparameters(batch_size=64, learning_rate=3e-3)
    return network, BehavioralCloning(network, given, hyper, expert_steps(tmp_path / "e.demo"))


def test_continuous_actions_are_cloned_as_unity_receives_them(tmp_path) -> None:
    network, bc = cloning(tmp_path, CONTINUOUS)
    critic = {n: p.detach().clone() for n, p in network.named_parameters() if "critic" in n}
    first = bc.update(steps=0)[REPORT]
    for _ in range(40):
        last = bc.update(steps=0)[REPORT]
    assert last < first / 4
    obs = {network.sensor_names[0]: torch.as_tensor(bc.obs[network.sensor_names[0]])}
    continuous, _, _ = network.act(obs, deterministic=True)
    sent = network.unity_action(continuous)
    assert float((sent - bc.continuous).square().mean()) < 0.02  # what Unity gets: the expert's
    for name, before in critic.items():
        assert torch.equal(dict(network.named_parameters())[name], before), name


def test_discrete_choices_are_cloned(tmp_path) -> None:
    network, bc = cloning(tmp_path, DISCRETE, num_epoch=2)
    for _ in range(30):
        bc.update(steps=0)
    _, discrete, _ = network.act(dict(bc.obs), deterministic=True)
    assert float((discrete == bc.discrete).float().mean()) > 0.9


def test_a_policy_with_memory_is_cloned_on_sequences_from_zero_memory(tmp_path) -> None:
    network, bc = cloning(tmp_path, DISCRETE, MemorySettings(16, 8), num_epoch=2)
    critic = {n: p.detach().clone() for n, p in network.named_parameters() if "critic" in n}
    assert any("critic_lstm" in name for name in critic)
    for _ in range(30):
        bc.update(steps=0)
    memory, right = None, []
    for row in range(64):  # acting as a worker does, memory carried from step to step
        obs = {name: values[row : row + 1] for name, values in bc.obs.items()}
        _, discrete, _, memory = network.act_recurrent(obs, None, memory, deterministic=True)
        right.append(bool((discrete[0] == bc.discrete[row]).all()))
    assert np.mean(right) > 0.9
    for name, before in critic.items():
        assert torch.equal(dict(network.named_parameters())[name], before), name


def test_the_rate_decays_over_steps_and_cloning_stops_there(tmp_path) -> None:
    network, bc = cloning(tmp_path, CONTINUOUS, steps=1000, strength=0.5)
    assert bc.lr == pytest.approx(1.5e-3)  # learning_rate x strength
    bc.update(steps=500)  # trains at 1.5e-3, then sets the rate for the next update
    assert bc.lr == pytest.approx(0.75e-3, rel=1e-6)
    bc.update(steps=1000)
    weights = {n: p.detach().clone() for n, p in network.named_parameters()}
    assert bc.update(steps=1200) == {REPORT: 0.0}
    assert all(torch.equal(p, weights[n]) for n, p in network.named_parameters())


def test_samples_per_update_bounds_each_pass(tmp_path) -> None:
    _, bc = cloning(tmp_path, CONTINUOUS, samples_per_update=128, num_epoch=1)
    steps = []
    bc.optimizer.step = lambda *a, **k: steps.append(1)  # count the optimizer's steps
    bc.update(steps=0)
    assert len(steps) == 2  # 128 samples in minibatches of 64 (512 would be 8)


def test_demonstrations_of_another_spec_are_refused_naming_the_file(tmp_path) -> None:
    write_demo(tmp_path / "other.demo", expert(CONTINUOUS, 20))
    other = spec([sensor((6,), "VectorSensor_size6")], continuous=3)
    path = str(tmp_path / "other.demo")
    config = parse_config({"behaviors": {"B": {"behavioral_cloning": {"demo_path": path}}}})
    learner = CentralLearner(config, experts={path: expert_steps(path)})
    with pytest.raises(ValueError, match=r"behavioral_cloning of B: .*other\.demo: actions"):
        learner.submit([segment(other, rows=1, steps=8, behavior="B")])
