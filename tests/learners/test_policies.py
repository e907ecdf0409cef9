"""Policies built from behavior specs (no Ray): the numpy acting path agrees with the
torch network, masks hold, weights reload."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec, ObservationSpec

from learners.acting.factory import PolicyFactory
from learners.acting.numpy_policy import NumpyActor, acts_in_numpy, encoder_width
from learners.networks.policies import ActorCritic, TorchActor, numpy_state
from learners.networks.sensors import RunningNorm, SensorEncoder
from learners.trainer_config.settings import NetworkSettings
from testkit.segments import GRID, IMAGE, VECTOR


def hybrid_spec(*sensors: ObservationSpec) -> BehaviorSpec:
    return BehaviorSpec(list(sensors), ActionSpec(2, (3, 2)))


def rollout_actor(network: ActorCritic, seed: int) -> NumpyActor | TorchActor:
    """What a worker would act with: numpy where it can, else the torch network."""
    if acts_in_numpy(network.spec, network.settings):
        return NumpyActor(network.spec, network.settings, numpy_state(network), seed=seed)
    return TorchActor(network)


def observations(spec: BehaviorSpec, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        o.name: rng.normal(size=(n, *o.shape)).astype(np.float32) for o in spec.observation_specs
    }


@pytest.mark.parametrize("normalize", [False, True], ids=["raw", "normalized"])
@pytest.mark.parametrize("sensors", [(VECTOR, GRID), (VECTOR, IMAGE)], ids=["vectors", "camera"])
def test_log_probs_agree_with_the_network(sensors, normalize):
    spec = hybrid_spec(*sensors)
    torch.manual_seed(0)
    network = ActorCritic(spec, NetworkSettings(normalize=normalize))
    obs = observations(spec, 64)
    if normalize:  # statistics far from the identity, so a mirror that skips them fails
        network.update_normalization({k: torch.from_numpy(v * 3 + 2) for k, v in obs.items()})
    actor = rollout_actor(network, seed=1)
    assert isinstance(actor, NumpyActor)  # cameras too: workers act without torch
    mask = np.ones((64, 5), bool)
    mask[:, 1] = False  # branch 0, action 1 forbidden
    continuous, discrete, log_prob = actor.act(obs, mask)
    assert continuous.shape == (64, 2) and continuous.dtype == np.float32
    assert discrete.shape == (64, 2) and discrete.dtype == np.int64
    assert log_prob.shape == (64, 4) and log_prob.dtype == np.float32  # 2 dims, 2 branches
    assert not (discrete[:, 0] == 1).any()
    with torch.no_grad():
        expected, _, _ = network.evaluate(
            {k: torch.from_numpy(v) for k, v in obs.items()},
            torch.from_numpy(continuous),
            torch.from_numpy(discrete),
            torch.from_numpy(mask),
        )
    np.testing.assert_allclose(log_prob, expected.numpy(), rtol=1e-4, atol=1e-4)


def test_discrete_samples_follow_the_masked_softmax():
    spec = BehaviorSpec([VECTOR], ActionSpec(0, (4,)))
    torch.manual_seed(0)
    network = ActorCritic(spec)
    actor = rollout_actor(network, seed=2)
    obs = {"vector": np.repeat(observations(spec, 1)["vector"], 20000, axis=0)}
    mask = np.ones((20000, 4), bool)
    mask[:, 3] = False
    _, discrete, _ = actor.act(obs, mask)
    with torch.no_grad():
        logits = network.logits(network.features({"vector": torch.from_numpy(obs["vector"][:1])}))
    probs = torch.softmax(logits.masked_fill(~torch.from_numpy(mask[:1]), float("-inf")), -1)[0]
    frequencies = np.bincount(discrete[:, 0], minlength=4) / 20000
    np.testing.assert_allclose(frequencies, probs.numpy(), atol=0.015)
    assert frequencies[3] == 0.0


def test_loading_weights_refreshes_the_numpy_mirror():
    spec = BehaviorSpec([VECTOR], ActionSpec(3, ()))
    network = ActorCritic(spec)
    actor = rollout_actor(network, seed=3)
    actor.load_state_dict({k: np.zeros_like(v) for k, v in numpy_state(network).items()})
    continuous, _, log_prob = actor.act(observations(spec, 5000))
    assert abs(continuous.mean()) < 0.05 and abs(continuous.std() - 1.0) < 0.05
    # log N(x; 0, 1) for each of the 3 dimensions
    np.testing.assert_allclose(log_prob, -0.5 * continuous**2 - 0.5 * np.log(2 * np.pi), rtol=1e-5)


def test_running_norm_matches_the_statistics_of_everything_it_saw():
    rng = np.random.default_rng(0)
    chunks = [rng.normal(loc=4.0, scale=3.0, size=(n, 5)) for n in (7, 100, 1, 40)]
    norm = RunningNorm(5)
    for chunk in chunks:
        norm.update(torch.from_numpy(chunk))
    everything = np.concatenate(chunks)
    np.testing.assert_allclose(norm.mean.numpy(), everything.mean(0), rtol=1e-4)
    np.testing.assert_allclose(norm.var.numpy(), everything.var(0), rtol=1e-3)
    out = norm(torch.from_numpy(everything).float())
    assert abs(float(out.mean())) < 1e-3 and abs(float(out.std()) - 1) < 1e-2
    assert float(norm(torch.full((1, 5), 1e6)).max()) == norm.clip


SQUASHED_FLAGS = {"tanh_squash": True, "conditional_sigma": True}


@pytest.mark.parametrize("normalize", [False, True], ids=["raw", "normalized"])
@pytest.mark.parametrize("sensors", [(VECTOR, GRID), (VECTOR, IMAGE)], ids=["vectors", "camera"])
def test_squashed_conditional_policy_agrees_with_the_network(sensors, normalize):
    """SAC's policy: actions are tanh of the sample, in (-1, 1), and the log-prob the
    workers store (with the tanh correction) is what ``evaluate`` gives the stored action."""
    spec = BehaviorSpec(list(sensors), ActionSpec(2, ()))
    torch.manual_seed(0)
    network = ActorCritic(spec, NetworkSettings(normalize=normalize, **SQUASHED_FLAGS))
    assert network.log_std is None and network.log_std_head is not None
    with torch.no_grad():  # a state-dependent spread well away from 1
        torch.nn.init.normal_(network.log_std_head.weight, std=0.05)
        network.log_std_head.bias.fill_(-0.5)
        torch.nn.init.normal_(network.mean.weight, std=0.05)
    obs = observations(spec, 256)
    if normalize:
        network.update_normalization({k: torch.from_numpy(v * 3 + 2) for k, v in obs.items()})
    actor = rollout_actor(network, seed=1)
    continuous, _, log_prob = actor.act(obs)
    assert np.abs(continuous).max() < 1.0 and continuous.std(0).min() > 0.05
    tensors = {k: torch.from_numpy(v) for k, v in obs.items()}
    with torch.no_grad():
        expected, _, _ = network.evaluate(tensors, torch.from_numpy(continuous), None)
        torch_continuous, _, torch_log_prob = network.act(tensors)
        again, _, _ = network.evaluate(tensors, torch_continuous, None)
        # the log-std differs per observation (conditional), within its clamp
        mean, log_std = network.mean_log_std(network.features(tensors))
    np.testing.assert_allclose(log_prob, expected.numpy(), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(torch_log_prob, again, rtol=1e-4, atol=1e-4)
    assert float(log_std.std(0).min()) > 0.01
    # By hand, in float64: log N(atanh(a); mean, std) - log(1 - a^2), per dimension.
    a = continuous.astype(np.float64)
    u, std = np.arctanh(a), np.exp(log_std.double().numpy())
    gaussian = -0.5 * ((u - mean.double().numpy()) / std) ** 2 - np.log(std * np.sqrt(2 * np.pi))
    by_hand = gaussian - np.log1p(-(a**2))
    np.testing.assert_allclose(log_prob, by_hand, rtol=1e-3, atol=1e-3)
    # Deterministic acting is tanh(mean).
    with torch.no_grad():
        deterministic, _, _ = network.act(tensors, deterministic=True)
        mean, _ = network.mean_log_std(network.features(tensors))
    torch.testing.assert_close(deterministic, torch.tanh(mean))


def test_default_settings_keep_the_state_independent_unsquashed_gaussian():
    network = ActorCritic(hybrid_spec(VECTOR))
    assert network.log_std is not None and network.log_std_head is None
    assert "log_std_head.weight" not in network.state_dict()


def test_the_factory_builds_the_same_initial_weights_in_every_process():
    """Workers and the learner each build a behavior's network: from one seed and the
    behavior's name they start from the same weights, so data acted before the first
    update is on-policy for it. Other seeds and behaviors get other weights, and the
    caller's random stream is left as it was."""
    spec = hybrid_spec(VECTOR)
    torch.manual_seed(123)
    expected_next = torch.rand(1)
    torch.manual_seed(123)
    first = PolicyFactory(seed=7).network("A?team=0", spec).state_dict()
    assert torch.equal(torch.rand(1), expected_next)
    torch.manual_seed(999)  # another process's state
    again = PolicyFactory(seed=7).network("A?team=0", spec).state_dict()
    for other in (
        PolicyFactory(seed=8).network("A?team=0", spec),
        PolicyFactory(seed=7).network("B?team=0", spec),
    ):
        assert not torch.equal(other.state_dict()["mean.weight"], first["mean.weight"])
    assert first.keys() == again.keys()
    assert all(torch.equal(first[k], again[k]) for k in first)


@pytest.mark.parametrize("shape", [(3, 84, 84), (3, 40, 40), (1, 20, 36), (8,), (2, 3)])
@pytest.mark.parametrize("vis_encode_type", ["simple", "resnet"])
def test_the_torch_free_width_of_an_encoder_is_what_it_gives(shape, vis_encode_type):
    settings = NetworkSettings(hidden_units=24, vis_encode_type=vis_encode_type)
    encoder = SensorEncoder(shape, settings)
    assert encoder_width(shape, settings) == encoder.size
    assert encoder(torch.rand(2, *shape)).shape == (2, encoder.size)


def test_workers_act_with_the_learners_initial_weights_and_ml_agents_initialization():
    """The factory a worker unpickles gives the numpy actor the weights the learner's
    network starts from (images: the torch network, the same too); the draws follow
    ML-Agents' initialization."""
    factory = PolicyFactory(seed=3)
    spec = hybrid_spec(VECTOR, GRID)
    network = factory.network("A", spec)
    actor = factory("A", spec)
    assert isinstance(actor, NumpyActor)
    obs = observations(spec, 32)
    tensors = {k: torch.from_numpy(v) for k, v in obs.items()}
    continuous, discrete, log_prob = actor.act(obs)
    with torch.no_grad():
        expected, _, _ = network.evaluate(
            tensors, torch.from_numpy(continuous), torch.from_numpy(discrete)
        )
    np.testing.assert_allclose(log_prob, expected.numpy(), rtol=1e-4, atol=1e-4)
    image_spec = hybrid_spec(VECTOR, IMAGE)
    image_actor = factory("B", image_spec)  # a camera: numpy too, the same weights
    assert isinstance(image_actor, NumpyActor)
    image_network = factory.network("B", image_spec)
    image_obs = observations(image_spec, 32)
    continuous, discrete, log_prob = image_actor.act(image_obs)
    with torch.no_grad():
        expected, _, _ = image_network.evaluate(
            {k: torch.from_numpy(v) for k, v in image_obs.items()},
            torch.from_numpy(continuous),
            torch.from_numpy(discrete),
        )
    np.testing.assert_allclose(log_prob, expected.numpy(), rtol=1e-4, atol=1e-4)

    wide = BehaviorSpec([ObservationSpec((400,), *VECTOR[1:3], "v")], ActionSpec(2, (3,)))
    state = factory.initial_weights("C", wide)
    trunk, head = state["trunk.0.weight"], state["mean.weight"]
    assert abs(trunk.std() * np.sqrt(400) - 1.0) < 0.02  # kaiming_normal, linear gain
    assert abs(head.std() * np.sqrt(128) / 0.2 - 1.0) < 0.15  # gain 0.2
    assert abs(state["value.weight"]).max() <= np.sqrt(6 / 129)  # xavier_uniform
    assert not state["trunk.0.bias"].any() and not state["log_std"].any()


@pytest.mark.parametrize("squash", [False, True], ids=["ppo", "sac"])
@pytest.mark.parametrize("sensors", [(VECTOR, GRID), (VECTOR, IMAGE)], ids=["vectors", "camera"])
def test_deterministic_acting_takes_the_mean_and_the_likeliest_action(sensors, squash):
    """network_settings.deterministic (the CLI's --deterministic), numpy or torch alike."""
    spec = hybrid_spec(*sensors)
    settings = NetworkSettings(deterministic=True, tanh_squash=squash, conditional_sigma=squash)
    torch.manual_seed(0)
    network = ActorCritic(spec, settings)
    obs = observations(spec, 16)
    mask = np.ones((16, 5), bool)
    mask[:, 0] = False
    first, second = rollout_actor(network, seed=1), rollout_actor(network, seed=2)
    continuous, discrete, log_prob = first.act(obs, mask)
    again = second.act(obs, mask)
    for ours, theirs in zip((continuous, discrete, log_prob), again, strict=True):
        np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-5)  # no draw at all
    with torch.no_grad():
        hidden = network.features({k: torch.from_numpy(v) for k, v in obs.items()})
        mean, _ = network.mean_log_std(hidden)
        logits = network.logits(hidden).masked_fill(~torch.from_numpy(mask), float("-inf"))
    expected = torch.tanh(mean) if squash else mean
    np.testing.assert_allclose(continuous, expected.numpy(), rtol=1e-4, atol=1e-5)
    likeliest = [logits[:, :3].argmax(-1), logits[:, 3:].argmax(-1)]
    np.testing.assert_array_equal(discrete, torch.stack(likeliest, -1).numpy())


@pytest.mark.parametrize("squash", [False, True], ids=["gaussian", "tanh"])
def test_evaluate_gives_the_densities_torch_distributions_give(squash):
    """``evaluate`` writes the densities out; they are torch's Normal and torchrl's
    MaskedCategorical (the masked action has probability 0), and a mask leaves the
    gradient finite."""
    from torch.distributions import Normal
    from torchrl.modules import MaskedCategorical

    spec = hybrid_spec(VECTOR)
    settings = NetworkSettings(hidden_units=16, tanh_squash=squash, conditional_sigma=squash)
    torch.manual_seed(0)
    network = ActorCritic(spec, settings)
    obs = {"vector": torch.randn(32, *VECTOR.shape)}
    mask = torch.ones(32, 5, dtype=torch.bool)
    mask[:, 1] = False  # the first branch's middle action is never allowed
    continuous, discrete, _ = network.act(obs, mask)
    log_prob, entropy, _ = network.evaluate(obs, continuous, discrete, mask)

    hidden = network.features(obs)
    mean, log_std = network.mean_log_std(hidden)
    normal = Normal(mean, log_std.exp())
    u = torch.atanh(continuous.clamp(-1 + 1e-6, 1 - 1e-6)) if squash else continuous
    expected_continuous = normal.log_prob(u)
    if squash:
        expected_continuous = expected_continuous - torch.log1p(-(torch.tanh(u) ** 2))
    logits = torch.split(network.logits(hidden), (3, 2), dim=-1)
    masks = torch.split(mask, (3, 2), dim=-1)
    branches = [MaskedCategorical(logits=lg, mask=m) for lg, m in zip(logits, masks, strict=True)]
    expected = torch.cat(
        [expected_continuous]
        + [b.log_prob(discrete[:, i]).unsqueeze(-1) for i, b in enumerate(branches)],
        dim=-1,
    )
    assert torch.allclose(log_prob, expected, atol=1e-4)
    expected_entropy = normal.entropy().mean(-1) + sum(b.entropy() for b in branches)
    assert torch.allclose(entropy, expected_entropy, atol=1e-5)
    (log_prob.sum() + entropy.sum()).backward()
    assert all(torch.isfinite(p.grad).all() for p in network.parameters() if p.grad is not None)
