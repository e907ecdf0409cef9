"""PPO and IMPALA without Ray: advantage and V-trace targets against hand-computed
cases, losses that go down on a fixed batch, stale steps dropped, the learner's
versions and per-behavior policy lag."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
import pytest
import torch

from batches import keys
from batches.segment import Segment, Sources
from learners.algorithms.impala import IMPALA
from learners.algorithms.ppo import PPO, Steps
from learners.host.learner import CentralLearner, policy_lag
from learners.networks.policies import ActorCritic
from learners.networks.torchrl_views import add_flat_action
from learners.trainer_config.parse import defaults, parse_config
from learners.trainer_config.settings import NetworkSettings
from testkit.segments import segment, vector_spec
from tests.waiting import wait_for


def settings(trainer: str = "ppo", gamma: float = 0.9, **hyper):
    base = defaults(trainer)
    h = dataclasses.replace(base.hyperparameters, **hyper)
    return dataclasses.replace(base, hyperparameters=h, gamma=gamma)


def constant_value_network(spec, value: float = 0.5) -> ActorCritic:
    """Uniform policy (zero logits) and V(s) = value everywhere: hand-computable targets."""
    network = ActorCritic(spec, NetworkSettings(hidden_units=8, num_layers=1))
    with torch.no_grad():
        network.value.weight.zero_()
        network.value.bias.fill_(value)
        if network.logits is not None:
            network.logits.weight.zero_()
            network.logits.bias.zero_()
    return network


def on_policy(network: ActorCritic, batch):
    """Stamp each step with the log-probability the network gives its action."""
    actions = batch[keys.ACTION]
    continuous = actions.get(keys.CONTINUOUS, None)
    discrete = actions.get(keys.DISCRETE, None)
    with torch.no_grad():
        log_prob, _, _ = network.evaluate(
            {"vector": batch[keys.OBS, "vector"]},
            continuous,
            discrete,
            batch.get(keys.ACTION_MASK, None),
        )
    batch[keys.LOG_PROB] = log_prob
    return batch


def one_row(spec, rewards, terminated=(), truncated=()):
    """Packed steps of one agent, cut after the last (bootstrap there), with episode ends."""
    row = segment(spec, 1, len(rewards))
    row[keys.NEXT, keys.REWARD] = torch.tensor(rewards, dtype=torch.float32).view(-1, 1)
    for t in terminated:
        row[keys.NEXT, keys.TERMINATED][t] = True
        row[keys.NEXT, keys.DONE][t] = True
    for t in truncated:
        row[keys.NEXT, keys.TRUNCATED][t] = True
        row[keys.NEXT, keys.DONE][t] = True
    return add_flat_action(row.exclude(*keys.METADATA))


@pytest.mark.parametrize(
    ("end", "expected"),
    [("terminated", [0.59, -0.5, 1.95]), ("truncated", [0.914, -0.05, 1.95])],
)
def test_gae_matches_a_hand_computed_case(end, expected):
    # V = 0.5, gamma 0.9, lambda 0.8, rewards (1, 0, 2), the episode ends after step 1.
    # d0 = 1 + .9*.5 - .5 = .95; d1 = 0 - .5 (terminated) or 0 + .45 - .5 (truncated:
    # bootstrap from the final observation); d2 = 2 + .45 - .5 = 1.95 (row end: bootstrap)
    # A1 = d1 (the end cuts the trace); A0 = d0 + .9*.8*A1. Step 2 starts a new trajectory.
    spec = vector_spec(branches=(2,))
    ppo = PPO(constant_value_network(spec), settings(lambd=0.8))
    ppo.store.add(one_row(spec, [1.0, 0.0, 2.0], **{end: [1]}))
    with torch.no_grad():
        _, advantage, value_target = ppo.estimate(ppo.store.take())
    assert advantage.tolist() == pytest.approx(expected, abs=1e-5)
    assert value_target.tolist() == pytest.approx([a + 0.5 for a in expected], abs=1e-5)


def test_vtrace_matches_a_hand_computed_case():
    # Uniform policy over 2 actions: log pi = log .5. Behavior log-probs log .25 and log 1
    # give rho = 2 (clipped to 1) and .5. V = .5, gamma .9, rewards (1, 2), no end.
    # d0 = 1*(1 + .45 - .5) = .95; d1 = .5*(2 + .45 - .5) = .975
    # vs1 = .5 + .975 = 1.475; vs0 = .5 + .95 + .9*1*.975 = 2.3275
    # pg advantage: t0 = 1*(1 + .9*1.475 - .5) = 1.8275; t1 = .5*(2 + .9*.5 - .5) = .975
    spec = vector_spec(branches=(2,))
    impala = IMPALA(constant_value_network(spec), settings("impala"))
    row = one_row(spec, [1.0, 2.0])
    row[keys.LOG_PROB] = torch.tensor([[math.log(0.25)], [0.0]])
    impala.vtrace(row)
    assert row["value_target"].view(-1).tolist() == pytest.approx([2.3275, 1.475], abs=1e-5)
    assert row["advantage"].view(-1).tolist() == pytest.approx([1.8275, 0.975], abs=1e-5)


@pytest.mark.parametrize("trainer", ["ppo", "impala"])
@pytest.mark.parametrize(
    "actions", [{"continuous": 2}, {"branches": (3, 2)}, {"continuous": 1, "branches": (3,)}]
)
def test_losses_go_down_on_a_fixed_batch(trainer, actions):
    spec = vector_spec(**actions)
    torch.manual_seed(0)
    network = ActorCritic(spec, NetworkSettings(hidden_units=32, num_layers=2))
    algorithm = (PPO if trainer == "ppo" else IMPALA)(
        network, settings(trainer, batch_size=64, buffer_size=64, learning_rate=3e-3)
    )
    batch = on_policy(network, segment(spec, 8, 16, seed=1))
    # one-step episodes whose reward depends on the observation: a learnable value function
    batch[keys.NEXT, keys.REWARD] = batch[keys.OBS, "vector"][..., :1] * 2
    ends = torch.ones(8 * 16, 1, dtype=torch.bool)
    batch[keys.NEXT, keys.DONE], batch[keys.NEXT, keys.TERMINATED] = ends, ends.clone()
    batch[keys.NEXT, keys.TRUNCATED] = torch.zeros_like(ends)
    reports = []
    for _ in range(30 if trainer == "ppo" else 90):  # IMPALA: 1 epoch, PPO: 3
        algorithm.add(batch.clone(), torch.zeros(8 * 16, dtype=torch.int64))
        assert algorithm.ready()
        reports.append(algorithm.update(progress=0.0))
    first, last = reports[0], reports[-1]
    assert last["Losses/Value Loss"] < 0.5 * first["Losses/Value Loss"]
    assert last["Policy/Samples"] == 8 * 16
    assert math.isfinite(last["Losses/Policy Loss"]) and last["Policy/Entropy"] > 0
    assert all(r["Losses/Policy Loss"] > 0 for r in reports)  # each minibatch's |loss|


def test_policy_gradient_raises_the_log_prob_of_advantaged_actions():
    spec = vector_spec(branches=(3,))
    torch.manual_seed(0)
    network = ActorCritic(spec, NetworkSettings(hidden_units=16, num_layers=1))
    ppo = PPO(network, settings(batch_size=64, buffer_size=64, learning_rate=1e-2, beta=0.0))
    batch = on_policy(network, segment(spec, 8, 16, seed=2))
    chosen = batch[keys.ACTION, keys.DISCRETE][..., 0]
    batch[keys.NEXT, keys.REWARD] = (chosen == 2).float().unsqueeze(-1)  # action 2 pays
    obs = {"vector": batch[keys.OBS, "vector"]}
    before = torch.softmax(network.logits(network.features(obs)), -1)[..., 2].mean()
    for _ in range(20):
        ppo.add(batch.clone(), torch.zeros(8 * 16, dtype=torch.int64))
        ppo.update(progress=0.0)
    after = torch.softmax(network.logits(network.features(obs)), -1)[..., 2].mean()
    # the ratio to the behavior policy is clipped at 1 + epsilon (0.2): a bounded rise
    assert after > before * 1.15


@pytest.mark.parametrize(
    ("schedules", "epsilon", "beta"),
    [
        ({}, 0.1 + 0.1 * 0.25, 1e-5 + (0.01 - 1e-5) * 0.25),  # linear, as learning_rate
        ({"epsilon_schedule": "constant"}, 0.2, 1e-5 + (0.01 - 1e-5) * 0.25),
        ({"learning_rate_schedule": "constant"}, 0.2, 0.01),  # both follow it
        ({"learning_rate_schedule": "constant", "beta_schedule": "linear"}, 0.2, 0.0025075),
    ],
)
def test_epsilon_and_beta_decay_as_in_mlagents(schedules, epsilon, beta):
    # ML-Agents: linear from the value to 0.1 (epsilon) and 1e-5 (beta) at max_steps;
    # *_schedule defaults to learning_rate_schedule.
    spec = vector_spec(continuous=2)
    ppo = PPO(ActorCritic(spec), settings(beta=0.01, batch_size=16, buffer_size=32, **schedules))
    ppo.add(segment(spec, 3, 16), torch.zeros(48, dtype=torch.int64))
    report = ppo.update(progress=0.75)
    assert report["Policy/Epsilon"] == pytest.approx(epsilon)
    assert report["Policy/Beta"] == pytest.approx(beta)


def test_ppo_clips_each_action_component_not_the_value_as_mlagents_learn():
    """ML-Agents' trust region: each component's ratio is clipped on its own and the
    clipped surrogates averaged; the value loss is the plain squared error (mlagents-learn
    1.1.0's value clip never binds). Hand-computed on a policy N(0, 1) per dimension and a
    uniform branch of 2."""
    spec = vector_spec(continuous=2, branches=(2,))
    network = constant_value_network(spec, value=1.0)
    with torch.no_grad():
        network.mean.weight.zero_()
    ppo = PPO(network, settings())
    steps = segment(spec, 1, 2)
    steps[keys.ACTION, keys.CONTINUOUS] = torch.zeros(2, 2)
    steps[keys.ACTION, keys.DISCRETE] = torch.zeros(2, 1, dtype=torch.int64)
    now = torch.tensor([-0.5 * math.log(2 * math.pi)] * 2 + [math.log(0.5)])  # current log-probs
    # step 0: ratios (1.5, 1, 0.5) at advantage +1; step 1: ratios (1, 1, 1) at advantage -1
    steps[keys.LOG_PROB] = torch.stack([now - torch.log(torch.tensor([1.5, 1.0, 0.5])), now])
    ppo.store.add(steps)
    advantage, value_target = torch.tensor([1.0, -1.0]), torch.tensor([2.0, 0.0])  # V is 1.0
    losses = ppo.loss(Steps.of(ppo.store.take(), advantage, value_target), epsilon=0.2, beta=0.0)
    # step 0: mean(min(1.5, 1.2), 1, 0.5) = 0.9 (the joint ratio 0.75 would give 0.75);
    # step 1: -1 for each component
    assert float(losses["loss_objective"].detach()) == pytest.approx(-(0.9 - 1.0) / 2)
    assert float(losses["clip_fraction"]) == pytest.approx(2 / 6)
    # (2 - 1)^2 and (0 - 1)^2: no clip around an old estimate. Weighted 0.5, as in ML-Agents.
    assert float(losses["loss_critic"].detach()) == pytest.approx(0.5 * (1.0 + 1.0) / 2)


def test_ppo_normalizes_advantages_and_reports_its_policy_loss_as_mlagents(monkeypatch):
    """ML-Agents divides the advantages by numpy's std (no Bessel correction) and reports
    the mean over minibatches of each one's |policy loss|. With weights that do not move
    (ratio 1), a minibatch's loss is minus its mean normalized advantage: hand-computable."""
    spec = vector_spec(branches=(3,))
    torch.manual_seed(0)
    network = ActorCritic(spec, NetworkSettings(hidden_units=8, num_layers=1))
    ppo = PPO(network, settings(batch_size=16, buffer_size=47, num_epoch=1, learning_rate=0.0))
    batch = on_policy(network, segment(spec, 3, 16, seed=4))
    ppo.add(batch, torch.zeros(48, dtype=torch.int64))
    monkeypatch.setattr(torch, "randperm", lambda n, device=None: torch.arange(n, device=device))
    twin = copy.deepcopy(ppo)
    with torch.no_grad():
        _, advantage, _ = twin.estimate(twin.store.take())
    normalized = (advantage - advantage.mean()) / advantage.std(correction=0)
    expected = normalized.reshape(3, 16).mean(-1).abs().mean()  # three minibatches in order
    report = ppo.update(progress=0.0)
    assert report["Losses/Policy Loss"] == pytest.approx(float(expected), rel=1e-4)
    assert report["Losses/Policy Loss"] > 0.01  # the signed mean over minibatches is 0


def test_ppo_drops_steps_older_than_max_policy_lag():
    spec = vector_spec(continuous=2)
    ppo = PPO(ActorCritic(spec), settings(max_policy_lag=2, batch_size=8, buffer_size=16))
    lag = torch.tensor([0, 1, 2, 3, 4, 5, 0, 0])
    assert ppo.add(segment(spec, 1, 8), lag) == 5
    assert ppo.stale_steps == 3 and ppo.store.train_steps == 5 and not ppo.ready()


def test_ppo_trains_on_every_step_by_default_as_mlagents_learn():
    spec = vector_spec(continuous=2)
    ppo = PPO(ActorCritic(spec), settings(batch_size=8, buffer_size=16))
    assert ppo.add(segment(spec, 1, 8), torch.tensor([0, 1, 2, 3, 4, 5, 30, 0])) == 8
    assert ppo.stale_steps == 0 and ppo.store.train_steps == 8


def test_policy_lag_counts_only_the_behaviors_own_updates():
    # this behavior updated at global versions 1, 3 and 4 (another behavior made 2)
    lag = policy_lag([1, 3, 4], torch.tensor([0, 1, 2, 3, 4]))
    assert lag.tolist() == [3, 2, 2, 1, 0]
    assert policy_lag([], torch.tensor([0, 7])).tolist() == [0, 0]


SMALL = {"batch_size": 32, "buffer_size": 64}


def test_learner_versions_weights_and_checkpoint_round_trip():
    config = parse_config(
        {
            "behaviors": {
                "A": {
                    "trainer_type": "ppo",
                    "hyperparameters": {"batch_size": 32, "buffer_size": 64},
                },
                "B": {
                    "trainer_type": "impala",
                    "hyperparameters": {"batch_size": 32, "buffer_size": 64},
                },
            }
        }
    )
    learner = CentralLearner(config)
    specs = {"A?team=0": vector_spec(continuous=2), "B?team=0": vector_spec(branches=(3,))}
    assert learner.submit([]) == (0, None)  # no on-policy behavior seen yet
    # an update waits for more than buffer_size (64) steps, as in ML-Agents
    assert learner.submit([segment(specs["A?team=0"], 2, 16, "A?team=0")]) == (0, 33)
    version, wanted = learner.submit(
        [segment(s, 5, 16, name) for name, s in specs.items()]  # both pass their buffer
    )
    # PPO updated on 32 + 48 steps (the third trajectory tipped it); the last two wait
    assert version == 2 and wanted == 65 - 32  # for its next update; IMPALA wants no pause
    progress = learner.progress()
    assert progress["steps"] == {"A?team=0": 112, "B?team=0": 80}
    assert not progress["done"]
    assert [b for b, _, _ in learner.drain_reports()] == ["A?team=0", "B?team=0"]
    _, weights = learner.weights()
    assert set(weights) == set(specs)

    restored = CentralLearner(config)
    restored.load_state_dict(learner.state_dict())
    assert restored.version == 2 and restored.progress()["steps"] == progress["steps"]
    for name in specs:
        for key, value in restored.weights()[1][name].items():
            assert isinstance(value, np.ndarray)  # workers load them without torch
            np.testing.assert_array_equal(value, weights[name][key], err_msg=key)
    assert restored.behaviors["A?team=0"].updates == [1]


def test_hybrid_actions_are_shaped_right_and_masks_hold_in_the_torchrl_actor():
    from learners.networks.torchrl_views import FLAT_ACTION, probabilistic_actor

    spec = vector_spec(continuous=2, branches=(3, 2))
    network = ActorCritic(spec)
    actor = probabilistic_actor(network)
    batch = segment(spec, 64, 8)
    batch[keys.ACTION_MASK][..., 1] = False  # branch 0, action 1 forbidden
    dist = actor.get_dist(batch.exclude(*keys.METADATA))
    sample = dist.sample()
    assert sample.shape == (64 * 8, 2 + 2)  # 2 continuous + one index per branch
    assert not (sample[..., 2] == 1).any()
    assert set(sample[..., 2].unique().tolist()) == {0.0, 2.0}
    assert set(sample[..., 3].unique().tolist()) == {0.0, 1.0}
    assert dist.log_prob(sample).shape == (64 * 8,)
    assert dist.entropy().shape == (64 * 8,)
    flat = add_flat_action(batch.exclude(*keys.METADATA))[FLAT_ACTION]
    assert flat.shape == (64 * 8, 4)
    forbidden = flat.clone()
    forbidden[..., 2] = 1.0
    assert (dist.log_prob(forbidden) < -1e6).all()  # zero probability


def as_segment(batch, source) -> Segment:
    """A fake TensorDict segment as workers send it (numpy, with its source)."""

    def numpy(tree):
        return {k: numpy(v) if isinstance(v, dict) else v.numpy() for k, v in tree.items()}

    data = numpy(batch.exclude(*keys.METADATA).to_dict())
    return Segment(
        batch.get_non_tensor(keys.BEHAVIOR), batch.get_non_tensor(keys.SPEC), data, source
    )


def test_a_segment_delivered_twice_is_taken_once():
    learner = CentralLearner(parse_config({"behaviors": {"A": {"trainer_type": "ppo"}}}))
    spec = vector_spec(continuous=2)
    first = as_segment(segment(spec, 2, 16, "A?team=0"), ("worker-x", 1))
    second = as_segment(segment(spec, 1, 16, "A?team=0", seed=1), ("worker-x", 2))
    learner.submit([first, second, first])  # Ray retried the first delivery
    learner.submit([second])
    assert learner.progress()["steps"] == {"A?team=0": 48}
    assert learner.stats.duplicate_steps == 48
    # the same numbers from another incarnation (a restarted worker) are new
    learner.submit([as_segment(segment(spec, 1, 16, "A?team=0"), ("worker-y", 1))])
    assert learner.progress()["steps"] == {"A?team=0": 64}


def test_sources_stay_small_when_deliveries_come_in_order():
    sources = Sources()
    spec = vector_spec(continuous=2)
    batch = segment(spec, 1, 4, "A?team=0")
    for number in [2, 1, *range(3, 500)]:
        assert sources.first(as_segment(batch, ("w", number)))
    assert not sources.first(as_segment(batch, ("w", 7)))
    assert sources._taken[("w", "A?team=0")] == (499, set())


def test_progress_counts_the_update_under_way(monkeypatch):
    """The learner's busy time, read while an update runs (its Ray actor answers progress
    from another thread), includes that update so far: a window's busy fraction never
    takes a whole update at once."""
    import threading

    learner = CentralLearner(parse_config({"behaviors": {"A": {"trainer_type": "ppo"}}}))
    spec = vector_spec(continuous=2)
    learner.submit([as_segment(segment(spec, 1, 16, "A?team=0"), ("w", 1))])
    state = learner.behaviors["A?team=0"]
    started, release = threading.Event(), threading.Event()

    def slow_update(progress: float) -> dict[str, float]:
        started.set()
        release.wait(60)
        return {}

    monkeypatch.setattr(state.algorithm, "update", slow_update)
    before = learner.stats.update_seconds
    worker = threading.Thread(target=learner._update, args=("A?team=0", state))
    worker.start()
    assert started.wait(60)
    busy = lambda: learner.progress()["stats"].update_seconds > before  # noqa: E731
    wait_for(busy, "the update under way in progress()", 60)
    during = learner.progress()["stats"].update_seconds
    assert learner.stats.update_seconds == before, "the update has not ended: it is counted so far"
    release.set()
    worker.join(60)
    assert before < during <= learner.stats.update_seconds
