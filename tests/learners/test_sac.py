"""SAC (no Ray): Q losses fall on a fixed batch, masks hold in acting and in the target,
unsupported action spaces fail in one line, checkpoints round-trip, the update schedule,
and a short in-process run on unitysim 3DBall that clearly beats the random policy."""

from __future__ import annotations

import io
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from batches import keys
from learners.acting.factory import policy_factory
from learners.acting.numpy_policy import NumpyActor
from learners.algorithms.sac import MAX_GRADIENT_STEPS, SAC
from learners.algorithms.sac_terms import masked_logits, next_mask, taken
from learners.networks.policies import ActorCritic, numpy_state
from learners.trainer_config.parse import defaults, load_config
from learners.trainer_config.settings import NetworkSettings
from rollout.environment.ports import PortRange
from testkit.segments import segment, vector_spec
from tests.helpers import train_in_process

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
SAC_STEP_BUDGET = 60_000  # agent steps; measured need: see the test


def settings(gamma: float = 0.99, **hyper: float):
    base = defaults("sac")
    return replace(
        base,
        gamma=gamma,
        hyperparameters=replace(base.hyperparameters, batch_size=64, **hyper),
        network_settings=NetworkSettings(32, 2, normalize=True),
    )


def build(spec, seed: int = 0, gamma: float = 0.99, **hyper: float) -> SAC:
    torch.manual_seed(seed)
    trainer = settings(gamma, **hyper)
    squashed = replace(trainer.network_settings, tanh_squash=True, conditional_sigma=True)
    return SAC(ActorCritic(spec, squashed), trainer)


def floats(report: dict[str, torch.Tensor]) -> dict[str, float]:
    return {key: float(value) for key, value in report.items()}


def no_lag(batch) -> torch.Tensor:
    return torch.zeros(batch.batch_size, dtype=torch.int64)


def masked_segment(spec, rows: int = 8, steps: int = 16):
    """Action 3 of the single branch is forbidden on every step; a few episode ends."""
    batch = segment(spec, rows, steps)
    batch[keys.ACTION_MASK][..., 3] = False
    batch[keys.ACTION, keys.DISCRETE] = torch.randint(0, 3, (rows * steps, 1))
    batch[keys.NEXT, keys.DONE][5::steps] = True
    batch[keys.NEXT, keys.TERMINATED][5::steps] = True
    return batch


@pytest.mark.parametrize("kind", ["continuous", "discrete"])
def test_q_losses_fall_on_a_fixed_batch(kind):
    spec = vector_spec(6, continuous=2) if kind == "continuous" else vector_spec(6, branches=(4,))
    # A short horizon and little entropy noise: the bootstrapped targets settle fast.
    sac = build(spec, gamma=0.5, learning_rate=1e-3, init_entcoef=0.01)
    data = segment(spec, 8, 16)
    sac.add(data, no_lag(data))
    batch = sac.buffer.sample()
    first = floats(sac.gradient_step(batch.clone()))  # each Q's loss before the step
    for _ in range(150):
        last = floats(sac.gradient_step(batch.clone()))
    assert last["q1"] < 0.6 * first["q1"] and last["q2"] < 0.6 * first["q2"]
    assert np.isfinite(list(last.values())).all()


def test_masked_actions_are_never_sampled_and_weigh_nothing_in_the_target():
    spec = vector_spec(6, branches=(4,))
    sac = build(spec)
    data = masked_segment(spec)
    sac.add(data, no_lag(data))
    for _ in range(20):  # trained, so the check is not only about the initial weights
        sac.gradient_step(sac.buffer.sample())

    # Acting (the workers' numpy path): action 3 never comes out.
    actor = NumpyActor(spec, sac.network.settings, numpy_state(sac.network), seed=0)
    obs = {"vector": np.random.default_rng(0).normal(size=(5000, 6)).astype(np.float32)}
    mask = np.ones((5000, 4), bool)
    mask[:, 3] = False
    _, discrete, _ = actor.act(obs, mask)
    assert not (discrete == 3).any() and len(np.unique(discrete)) == 3

    # The target: the policy's next-state distribution gives action 3 probability 0, so
    # even a huge target Q for it leaves the target unchanged (steps whose next state is
    # unmasked, after an episode end or at a row end, do change).
    batch = sac.buffer.sample()
    nxt = batch[keys.NEXT]
    with torch.no_grad():
        logits = sac.policy(nxt[keys.OBS, "vector"])[0]
        probs = torch.softmax(masked_logits(logits, nxt[keys.ACTION_MASK]), dim=-1)
    blocked = ~nxt[keys.ACTION_MASK][:, 3]
    assert blocked.any() and (~blocked).any()
    assert (probs[blocked, 3] == 0).all() and (probs[~blocked, 3] > 0).all()
    alpha = sac.log_alpha.detach().exp()
    before = sac.target(batch, alpha)
    for q in sac.q_target:
        q.body[-1].bias.data[3] += 100.0
    after = sac.target(batch, alpha)
    torch.testing.assert_close(after[blocked], before[blocked])
    unmasked_next = ~blocked & ~batch[keys.NEXT, keys.TERMINATED][:, 0]
    assert unmasked_next.any() and (after[unmasked_next] > before[unmasked_next]).all()


def test_next_mask_is_the_next_steps_mask_within_the_trajectory():
    mask = torch.zeros(4, 2, dtype=torch.bool)
    mask[:, 0] = True  # every step: action 1 forbidden
    done = torch.tensor([False, True, True, True]).unsqueeze(-1)  # episode end, a cut, end
    result = next_mask(mask, done)
    assert result[0].tolist() == [True, False]  # step 1 follows in the same trajectory
    assert result[1].tolist() == [True, True]  # episode ended: no mask seen for it
    assert result[2].tolist() == [True, True]  # cut at the horizon: the next is elsewhere
    assert result[3].tolist() == [True, True]  # the segment's end


def test_a_behavior_without_actions_fails_in_one_line():
    with pytest.raises(ValueError, match=r"^SAC needs actions: this behavior has none$"):
        SAC(ActorCritic(vector_spec(4)), settings())


def hybrid_segment(spec):
    """Branch 0's action 2 forbidden on every step, a few episode ends."""
    batch = segment(spec, 8, 16)
    batch[keys.ACTION_MASK][..., 2] = False
    batch[keys.ACTION, keys.DISCRETE] = torch.stack(
        [torch.randint(0, 2, (128,)), torch.randint(0, 2, (128,))], dim=-1
    )
    batch[keys.NEXT, keys.DONE][5::16] = True
    batch[keys.NEXT, keys.TERMINATED][5::16] = True
    return batch


@pytest.mark.parametrize("continuous", [2, 0], ids=["hybrid", "2-branch"])
def test_several_branches_and_hybrid_actions_as_mlagents_condenses_them(continuous):
    """ML-Agents' SAC on GridFoodCollector (hybrid) and WallJump (4 branches): Q(s, a) is
    the mean over branches of each branch's value of its action, each branch has its own
    entropy coefficient and target, masked actions never enter the target, and a few
    steps lower the Q losses."""
    spec = vector_spec(6, continuous=continuous, branches=(3, 2))
    sac = build(spec)
    assert sac.log_alpha.shape == (int(bool(continuous)) + 2,)
    expected = [math.log(3) * 0.2, math.log(2) * 0.2]
    assert sac.target_entropy.tolist()[-2:] == pytest.approx(expected)
    data = hybrid_segment(spec)
    sac.add(data, no_lag(data))
    batch = sac.buffer.sample()
    obs = batch[keys.OBS, "vector"]
    stored = [batch["continuous_action"]] if continuous else []
    values = torch.stack([q(obs, *stored) for q in sac.q])
    a = batch["discrete_action"]
    by_hand = (
        values[..., :3].gather(-1, a[:, :1].expand(2, -1, 1)).squeeze(-1)
        + values[..., 3:].gather(-1, a[:, 1:].expand(2, -1, 1)).squeeze(-1)
    ) / 2
    streams = values.unsqueeze(-2)  # the extrinsic stream alone
    torch.testing.assert_close(taken(streams, a, sac.branches)[..., 0], by_hand)
    alpha = sac.log_alpha.detach().exp()
    before = sac.target(batch, alpha) if not continuous else None
    if before is not None:  # no sampling: the masked action's value cannot matter
        for q in sac.q_target:
            q.body[-1].bias.data[2] += 100.0
        blocked = ~batch[keys.NEXT, keys.ACTION_MASK][:, 2]  # (a trajectory's end: no mask)
        assert blocked.any()
        torch.testing.assert_close(sac.target(batch, alpha)[blocked], before[blocked])
    first = floats(sac.gradient_step(batch))
    for _ in range(30):
        last = floats(sac.gradient_step(batch))
    assert last["q1"] < first["q1"] and last["q2"] < first["q2"]
    assert all(math.isfinite(v) for v in last.values())
    moved = sac.log_alpha.detach()
    assert len(set(moved.tolist())) == len(moved), "each part's coefficient moves on its own"


@pytest.mark.parametrize("kind", ["continuous", "discrete"])
def test_state_dict_round_trip(kind):
    spec = vector_spec(6, continuous=2) if kind == "continuous" else vector_spec(6, branches=(4,))
    sac = build(spec, seed=0)
    data = segment(spec, 8, 16)
    sac.add(data, no_lag(data))
    for _ in range(5):
        sac.gradient_step(sac.buffer.sample())
    buffer = io.BytesIO()  # as checkpoints store it
    torch.save({"network": sac.network.state_dict(), "algorithm": sac.state_dict()}, buffer)
    buffer.seek(0)
    saved = torch.load(buffer, weights_only=False)

    other = build(spec, seed=1)  # different initial weights everywhere
    other.network.load_state_dict(saved["network"])
    other.load_state_dict(saved["algorithm"])
    torch.testing.assert_close(other.q.state_dict(), sac.q.state_dict())
    torch.testing.assert_close(other.q_target.state_dict(), sac.q_target.state_dict())
    initial = math.log(sac.settings.hyperparameters.init_entcoef)
    assert float(other.log_alpha.detach()) == float(sac.log_alpha.detach()) != initial
    old = {**saved["algorithm"], "log_alpha": sac.log_alpha.detach()[0]}  # scalar, as before
    other.load_state_dict(old)  # 2026-11-26's checkpoints: a scalar coefficient
    # Same batch, same noise: the next step (optimizer moments included) is identical.
    batch = sac.buffer.sample()
    torch.manual_seed(7)
    expected = floats(sac.gradient_step(batch.clone()))
    torch.manual_seed(7)
    got = floats(other.gradient_step(batch.clone()))
    assert got == pytest.approx(expected, rel=1e-5)
    torch.testing.assert_close(other.network.state_dict(), sac.network.state_dict())


def test_ready_waits_for_the_buffer_then_counts_new_steps_and_caps_updates():
    spec = vector_spec(4, continuous=1)
    sac = build(spec, buffer_init_steps=200, steps_per_update=0.5)
    data = segment(spec, 4, 32)  # 128 steps
    sac.add(data, no_lag(data))
    assert not sac.ready()  # 128 < buffer_init_steps
    sac.add(data, no_lag(data))
    assert sac.ready() and sac.new_steps == 56  # only the steps past the warm-up count
    report = sac.update(0.0)
    assert report["Policy/Gradient Steps"] == 112 and report["Policy/Samples"] == 112 * 64
    assert not sac.ready()
    for _ in range(2):
        sac.add(data, no_lag(data))  # 256 new steps owe 512 gradient steps
    report = sac.update(0.0)
    assert report["Policy/Gradient Steps"] == MAX_GRADIENT_STEPS
    assert report["Policy/Dropped Gradient Steps"] == 512 - MAX_GRADIENT_STEPS
    assert {"Losses/Q1 Loss", "Losses/Q2 Loss", "Policy/Entropy Coeff"} <= report.keys()


def test_sac_behaviors_get_the_squashed_policy_everywhere():
    config = load_config(CONFIG_DIR / "3DBall_sac.yaml")
    factory = policy_factory(config)
    network = factory.network("3DBall?team=0", vector_spec(8, continuous=2))
    assert network.settings.tanh_squash and network.settings.conditional_sigma
    assert network.log_std is None and network.log_std_head is not None
    actor = factory("3DBall?team=0", vector_spec(8, continuous=2))  # what workers build
    assert actor.settings == network.settings
    ppo = policy_factory(load_config(CONFIG_DIR / "3DBall.yaml"))
    assert not ppo.network("3DBall?team=0", vector_spec(8, continuous=2)).settings.tanh_squash


SAFETY_STOP_S = 900  # only a hung run gets here; a busy machine is slower, same steps


@pytest.mark.integration
@pytest.mark.timeout(SAFETY_STOP_S + 60)  # pytest's 300 s would stop a slow machine first
def test_sac_learns_3dball_in_process(tmp_path):
    """SAC on unitysim 3DBall within a budget of agent steps: mean return well above
    random (about 2). The wall-time cap only stops a hung run; a busy machine is slower
    but takes the same number of steps."""
    best, history = train_in_process(
        CONFIG_DIR / "3DBall_sac.yaml",
        "unitysim:3DBall",
        "3DBall?team=0",
        step_budget=SAC_STEP_BUDGET,
        goal=10,
        safety_stop_s=SAFETY_STOP_S,
        ports=PortRange(24600, 24649),
        registry=tmp_path / "ports",
    )
    print("(agent steps, episodes, best mean return):", history)
    assert best >= 10, f"(agent steps, episodes, best mean return): {history}"


class _MaskedSoftmax(torch.distributions.Categorical):
    def __init__(self, logits: torch.Tensor, mask: torch.Tensor) -> None:
        super().__init__(logits=masked_logits(logits, mask), validate_args=False)


def torchrl_loss(sac: SAC):
    """torchrl's SACLoss / DiscreteSACLoss over the same policy and Q networks: the
    reference the written-out losses must match."""
    from tensordict.nn import ProbabilisticTensorDictModule as Prob
    from tensordict.nn import ProbabilisticTensorDictSequential as Seq
    from torchrl.data import Bounded
    from torchrl.modules import TanhNormal
    from torchrl.objectives import DiscreteSACLoss, SACLoss

    from learners.networks.torchrl_views import PolicyParams, TensorModule, obs_keys

    obs = obs_keys(sac.network)
    net = sac.network
    if sac.continuous:
        actor = Seq(
            TensorModule(PolicyParams(net), in_keys=obs, out_keys=["loc", "scale"]),
            Prob(in_keys=["loc", "scale"], out_keys=["action"], distribution_class=TanhNormal),
        )
        qs = [
            TensorModule(q, in_keys=[*obs, "action"], out_keys=["state_action_value"])
            for q in sac.q
        ]
        loss = SACLoss(
            actor,
            qs,
            loss_function="l2",
            alpha_init=sac.settings.hyperparameters.init_entcoef,
            action_spec=Bounded(-1.0, 1.0, shape=(net.continuous,)),
        )
    else:
        actor = Seq(
            TensorModule(PolicyParams(net), in_keys=obs, out_keys=["logits"]),
            Prob(
                in_keys={"logits": "logits", "mask": keys.ACTION_MASK},
                out_keys=["action"],
                distribution_class=_MaskedSoftmax,
            ),
        )
        qs = [TensorModule(q, in_keys=obs, out_keys=["action_value"]) for q in sac.q]
        loss = DiscreteSACLoss(
            actor,
            qs,
            action_space="categorical",
            num_actions=net.branches[0],
            loss_function="l2",
            alpha_init=sac.settings.hyperparameters.init_entcoef,
            target_entropy_weight=0.2,
        )
    loss.make_value_estimator(gamma=sac.settings.gamma)
    return loss


@pytest.mark.parametrize("kind", ["continuous", "discrete"])
def test_the_losses_are_torchrls_sac_losses(kind):
    """The same batch, weights and noise give torchrl's three losses (v2, two Qs, l2;
    discrete: masked, with episode ends) and the same entropy."""
    spec = vector_spec(6, continuous=2) if kind == "continuous" else vector_spec(6, branches=(4,))
    sac = build(spec, gamma=0.9, init_entcoef=0.3)
    data = segment(spec, 8, 16) if kind == "continuous" else masked_segment(spec)
    sac.add(data, no_lag(data))
    reference = torchrl_loss(sac)  # its target Qs: copies of the Qs, as sac.q_target
    batch = sac.buffer.sample()
    action = batch["continuous_action"] if kind == "continuous" else batch["discrete_action"][:, 0]
    torch.manual_seed(3)
    expected = reference(batch.clone().set("action", action))
    torch.manual_seed(3)
    got = floats(sac.gradient_step(batch.clone()))
    assert got["policy"] == pytest.approx(float(expected["loss_actor"]), rel=1e-5)
    assert got["q1"] + got["q2"] == pytest.approx(float(expected["loss_qvalue"]), rel=1e-5)
    assert got["alpha_loss"] == pytest.approx(float(expected["loss_alpha"]), rel=1e-5)
    assert got["entropy"] == pytest.approx(float(expected["entropy"]), rel=1e-5)
