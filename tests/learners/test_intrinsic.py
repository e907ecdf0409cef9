"""Reward signals besides the extrinsic one (``curiosity``, ``rnd``, ``gail``): read from
the config with ML-Agents' defaults, each signal's reward falling where it has trained
(and not elsewhere), GAIL's rising on the expert's kind of step, and PPO giving each its
own value head, gamma and bootstrap at an episode's end."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from batches.expert_steps import ExpertSteps
from learners.algorithms.ppo import PPO
from learners.host.devices import Compute
from learners.networks.policies import ActorCritic
from learners.reward_signals.base import Transitions
from learners.reward_signals.gail import GAIL
from learners.reward_signals.intrinsic import RND, Curiosity
from learners.trainer_config.parse import ConfigError, parse_config
from learners.trainer_config.settings import Hyperparameters, NetworkSettings, RewardSignalSettings
from testkit.segments import DEVICES, compute_of, segment, vector_spec

SMALL = NetworkSettings(hidden_units=32, num_layers=2)


def config(signals: dict, trainer: str = "ppo"):
    return parse_config({"behaviors": {"B": {"trainer_type": trainer, "reward_signals": signals}}})


def test_signals_are_read_with_ml_agents_defaults():
    b = config({"extrinsic": {}, "curiosity": {}, "rnd": {"strength": 0.01}}).behaviors["B"]
    curiosity, rnd = b.reward_signals
    assert (curiosity.kind, curiosity.learning_rate, curiosity.strength) == ("curiosity", 3e-4, 1.0)
    assert (rnd.kind, rnd.learning_rate, rnd.strength) == ("rnd", 1e-4, 0.01)
    assert rnd.network_settings == NetworkSettings()  # its own, ML-Agents' defaults
    custom = config({"rnd": {"network_settings": {"hidden_units": 64, "num_layers": 3}}})
    (rnd,) = custom.behaviors["B"].reward_signals
    assert (rnd.network_settings.hidden_units, rnd.network_settings.num_layers) == (64, 3)
    assert custom.behaviors["B"].reward_strength == 0.0  # no extrinsic named: none trained


def test_signals_of_other_trainers_are_reported_and_a_bad_key_is_an_error():
    poca = config({"extrinsic": {}, "curiosity": {}}, trainer="poca")
    assert poca.unsupported == ("behaviors.B.reward_signals.curiosity",)
    assert poca.behaviors["B"].reward_signals == ()
    sac = config(
        {"extrinsic": {}, "curiosity": {}}, trainer="sac"
    )  # learners/reward_signals/sac_streams.py
    assert sac.unsupported == () and sac.behaviors["B"].reward_signals[0].kind == "curiosity"
    with pytest.raises(ConfigError, match=r"reward_signals.rnd.strenght: unknown key"):
        config({"rnd": {"strenght": 0.1}})
    with pytest.raises(ConfigError, match=r"reward_signals.curiosity.gamma"):
        config({"curiosity": {"gamma": 1.5}})
    memory = {"network_settings": {"memory": {"memory_size": 64, "sequence_length": 8}}}
    with pytest.raises(ConfigError, match=r"rnd.network_settings.memory: .* have no memory"):
        config({"rnd": memory})
    assert config({"rnd": {"network_settings": {"memory": None}}}).unsupported == ()


def steps(obs: torch.Tensor, after: torch.Tensor, discrete: torch.Tensor) -> Transitions:
    return Transitions({"vector": obs}, {"vector": after}, None, discrete)


def test_rnd_rewards_fall_where_it_trained_only():
    torch.manual_seed(0)
    spec = vector_spec(4, branches=(2,))
    rnd = RND(spec, RewardSignalSettings("rnd", network_settings=SMALL, learning_rate=1e-3))
    seen = torch.randn(256, 4) * 0.1
    unseen = torch.randn(256, 4) * 0.1 + 3.0
    zeros = torch.zeros(256, 1, dtype=torch.int64)
    before = rnd.rewards(steps(seen, seen, zeros)).mean()
    for _ in range(300):
        rnd.update(steps(seen, seen, zeros))
    assert rnd.rewards(steps(seen, seen, zeros)).mean() < before / 10
    assert (
        rnd.rewards(steps(unseen, unseen, zeros)).mean()
        > 10 * rnd.rewards(steps(seen, seen, zeros)).mean()
    )


def test_curiosity_learns_a_transition_and_caps_its_reward():
    torch.manual_seed(0)
    spec = vector_spec(4, branches=(2,))
    settings = RewardSignalSettings("curiosity", strength=0.5, network_settings=SMALL)
    curiosity = Curiosity(spec, settings)
    obs = torch.randn(256, 4)
    action = torch.randint(0, 2, (256, 1))
    after = obs.roll(1, dims=-1) + action.float()  # the action decides the next state
    batch = steps(obs, after, action)
    assert torch.equal(curiosity.rewards(batch), torch.zeros(256))  # 0 before it updates
    first = curiosity.update(batch)
    assert float(curiosity.rewards(batch).max()) <= 1 / 0.5  # capped at 1 / strength
    for _ in range(300):
        last = curiosity.update(batch)
    assert last["Losses/Curiosity Forward Loss"] < first["Losses/Curiosity Forward Loss"] / 5
    assert last["Losses/Curiosity Inverse Loss"] < first["Losses/Curiosity Inverse Loss"] / 2


def ppo_with(
    signals: tuple[RewardSignalSettings, ...],
    experts: dict | None = None,
    compute: Compute | None = None,
) -> PPO:
    torch.manual_seed(0)
    spec = vector_spec(4, branches=(2,))
    settings = parse_config({}).default
    settings = type(settings)(
        hyperparameters=Hyperparameters(batch_size=8, buffer_size=16, num_epoch=1),
        network_settings=SMALL,
        reward_signals=signals,
    )
    policy = ActorCritic(spec, SMALL)
    if compute is not None:
        compute.place(policy)
    return PPO(policy, settings, compute=compute, experts=experts)


def test_each_signal_has_its_value_head_and_bootstraps_at_an_episodes_end():
    rnd = RewardSignalSettings("rnd", gamma=0.9, strength=0.5, network_settings=SMALL)
    ppo = ppo_with((rnd,))
    batch = segment(vector_spec(4, branches=(2,)), rows=2, steps=8)
    batch["next", "terminated"][7] = True  # the first trajectory ends its episode
    ppo.add(batch, torch.zeros(16, dtype=torch.int64))
    rows = ppo.store.take()
    with torch.no_grad():
        value, _, target = ppo.estimate(rows)
        assert value.shape == target.shape == (16, 2)
        end = {"vector": batch["next", "obs", "vector"][7:8]}
        end_value = ppo.network.value_of(ppo.network.encode(end), ppo.signals.heads)[0]
        intrinsic = ppo.signals.items[0].rewards(
            Transitions({"vector": rows.obs["vector"][7:8]}, end, None, None)
        )
    reward = rows.reward[7]
    assert float(target[7, 0]) == pytest.approx(float(reward))  # extrinsic: 0 past the end
    expected = 0.5 * float(intrinsic[0]) + 0.9 * float(end_value[1])  # rnd: bootstraps
    assert float(target[7, 1]) == pytest.approx(expected, rel=1e-4)


def test_an_update_trains_the_signal_and_reports_ml_agents_tags():
    ppo = ppo_with((RewardSignalSettings("curiosity", network_settings=SMALL),))
    ppo.add(segment(vector_spec(4, branches=(2,)), rows=3, steps=8), torch.zeros(24).long())
    report = ppo.update(progress=0.1)
    for tag in (
        "Losses/Curiosity Forward Loss",
        "Losses/Curiosity Inverse Loss",
        "Policy/Curiosity Value Estimate",
        "Policy/Curiosity Reward",
        "Policy/Extrinsic Value Estimate",
    ):
        assert tag in report, tag
    state = ppo.state_dict()
    again = ppo_with((RewardSignalSettings("curiosity", network_settings=SMALL),))
    again.load_state_dict(state)
    heads = zip(ppo.signals.heads.parameters(), again.signals.heads.parameters(), strict=True)
    assert all(torch.equal(mine, theirs) for mine, theirs in heads)
    assert again.signals.items[0].updated


def test_gail_is_read_with_its_demonstrations():
    (gail,) = (
        config({"gail": {"demo_path": "e.demo", "use_vail": True}}).behaviors["B"].reward_signals
    )
    assert (gail.kind, gail.learning_rate, gail.use_vail, gail.use_actions) == (
        "gail", 3e-4, True, False,
    )  # fmt: skip
    assert gail.demo_path.endswith("/e.demo")
    with pytest.raises(ConfigError, match=r"reward_signals.gail.demo_path: required"):
        config({"gail": {"strength": 0.1}})


def expert_steps_of(obs: torch.Tensor, discrete: torch.Tensor) -> ExpertSteps:
    n = len(obs)
    return ExpertSteps(
        "expert.demo",
        vector_spec(4, branches=(2,)),
        (obs.numpy(),),
        np.zeros((n, 0), np.float32),
        discrete.numpy(),
        np.zeros(n, bool),
    )


@pytest.mark.parametrize(("use_actions", "use_vail"), [(False, False), (True, True)])
def test_gail_rewards_the_experts_kind_of_step(use_actions, use_vail):
    torch.manual_seed(0)
    expert_obs, policy_obs = torch.randn(512, 4) + 1.5, torch.randn(512, 4) - 1.5
    ones, zeros = torch.ones(512, 1).long(), torch.zeros(512, 1).long()
    settings = RewardSignalSettings(
        "gail", network_settings=SMALL, use_actions=use_actions, use_vail=use_vail
    )
    gail = GAIL(vector_spec(4, branches=(2,)), settings, expert_steps_of(expert_obs, ones))
    policy = Transitions({"vector": policy_obs}, {}, None, zeros, torch.zeros(512, dtype=bool))
    expert = Transitions({"vector": expert_obs}, {}, None, ones, torch.zeros(512, dtype=bool))
    for _ in range(150):
        stats = gail.update(policy[torch.randint(512, (64,))])
    assert stats["Policy/GAIL Expert Estimate"] > stats["Policy/GAIL Policy Estimate"] + 0.3
    assert gail.rewards(expert).mean() > 2 * gail.rewards(policy).mean()
    assert ("Policy/GAIL Beta" in stats) == use_vail
    assert "Policy/GAIL Grad Mag Loss" in stats


def test_gail_refuses_demonstrations_of_another_spec():
    other = ExpertSteps(
        "walker.demo",
        vector_spec(6, continuous=2),
        (np.zeros((4, 6), np.float32),),
        np.zeros((4, 2), np.float32),
        np.zeros((4, 0), np.int64),
        np.zeros(4, bool),
    )
    gail = RewardSignalSettings("gail", network_settings=SMALL, demo_path="walker.demo")
    with pytest.raises(ValueError, match=r"reward_signals.gail: walker.demo: actions"):
        ppo_with((gail,), experts={"walker.demo": other})


def test_signals_train_beside_ppos_epochs_and_one_seed_gives_one_run():
    """On a CPU the signals' steps run in a thread beside PPO's epochs, drawing from a
    generator seeded from the global one: the signals and the policy both train, and two
    updates from one seed end with the same parameters, bit for bit."""
    gail = RewardSignalSettings("gail", network_settings=SMALL, demo_path="e.demo", use_vail=True)
    curiosity = RewardSignalSettings("curiosity", network_settings=SMALL)
    torch.manual_seed(1)
    experts = {"e.demo": expert_steps_of(torch.randn(64, 4), torch.ones(64, 1).long())}
    batch = segment(vector_spec(4, branches=(2,)), rows=4, steps=16)
    ends = []
    for _ in range(2):
        ppo = ppo_with((curiosity, gail), experts)
        start = [p.detach().clone() for p in ppo.signals.items[1].parameters()]
        policy = [p.detach().clone() for p in ppo.network.parameters()]
        ppo.add(batch.clone(), torch.zeros(64).long())
        report = ppo.update(progress=0.1)
        assert "Losses/GAIL Loss" in report and "Losses/Curiosity Forward Loss" in report
        trained = [p.detach().clone() for p in ppo.signals.items[1].parameters()]
        assert any(not torch.equal(a, b) for a, b in zip(start, trained, strict=True))
        now = [p.detach().clone() for p in ppo.network.parameters()]
        assert any(not torch.equal(a, b) for a, b in zip(policy, now, strict=True))
        ends.append([*trained, *now, *ppo.signals.items[0].parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*ends, strict=True))


@pytest.mark.parametrize("device", DEVICES)
def test_every_signal_trains_under_mixed_precision(device):
    """bfloat16 autocast in the policy's hidden layers beside curiosity, RND and GAIL (whose
    networks stay float32): every loss finite, every signal's network trained."""
    experts = {"e.demo": expert_steps_of(torch.randn(64, 4), torch.ones(64, 1).long())}
    signals = (
        RewardSignalSettings("curiosity", network_settings=SMALL),
        RewardSignalSettings("rnd", network_settings=SMALL),
        RewardSignalSettings("gail", network_settings=SMALL, demo_path="e.demo"),
    )
    ppo = ppo_with(signals, experts, compute_of(device, True))
    before = [[p.detach().clone() for p in item.parameters()] for item in ppo.signals.items]
    ppo.add(segment(vector_spec(4, branches=(2,)), rows=2, steps=8), torch.zeros(16).long())
    report = ppo.update(progress=0.1)
    for tag in ("Losses/Curiosity Forward Loss", "Losses/RND Loss", "Losses/GAIL Loss"):
        assert tag in report, tag
    assert all(np.isfinite(v) for v in report.values())
    for item, start in zip(ppo.signals.items, before, strict=True):
        now = list(item.parameters())
        assert any(not torch.equal(a, b) for a, b in zip(start, now, strict=True)), item
