"""POCA without Ray: the group critic's masking, the lambda-return over group and
groupmates' rewards, the bootstrap of an agent that leaves its group, an update with
ML-Agents' tags, and checkpoints. Segments come from the real segment builder, fed with
mlagents_envs' own DecisionSteps and TerminalSteps."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from mlagents_envs.base_env import DecisionSteps, TerminalSteps

from batches import keys
from learners.algorithms.poca import POCA
from learners.algorithms.trajectory_store import TrajectoryStore
from learners.host.devices import to_cpu
from learners.networks.group_critic import GroupCritic
from learners.networks.policies import ActorCritic
from learners.trainer_config.parse import defaults
from learners.trainer_config.settings import NetworkSettings
from rollout.collecting.decisions import Decisions
from rollout.collecting.segments import SegmentBuilder
from testkit.segments import DEVICES, compute_of, vector_spec

SPEC = vector_spec(3, branches=(2,))
NET = NetworkSettings(hidden_units=16, num_layers=1)


def settings(gamma: float = 0.9, **hyper):
    base = defaults("poca")
    h = dataclasses.replace(base.hyperparameters, **hyper)
    return dataclasses.replace(base, hyperparameters=h, gamma=gamma)


def group_game(
    episodes: int, seed: int = 0, leave: bool = True, builder: SegmentBuilder | None = None
) -> list:
    """Groups of three (group 1: agents 1-3, group 2: 4-6) playing 4-exchange episodes:
    rewards 0.1 each, a group reward of 1 at the end; with ``leave``, the third member of
    each group ends its episode one exchange early. New episodes bring new agent ids."""
    rng = np.random.default_rng(seed)
    builder = builder or SegmentBuilder("Knights?team=0", SPEC, horizon=16)
    out = []
    for episode in range(episodes):
        ids = {a: 10 * episode + a for a in range(1, 7)}
        alive = list(range(1, 7))
        for exchange in range(5):
            last = exchange == 4
            leaving = [3, 6] if leave and exchange == 3 else []
            ending = alive if last else leaving
            deciding = [] if last else [a for a in alive if a not in leaving]
            group_reward = 1.0 if last else 0.0
            decisions = _steps(DecisionSteps, deciding, ids, rng, 0.0)
            terminals = _steps(TerminalSteps, ending, ids, rng, group_reward)
            builder.observe(decisions, terminals)
            if (segment := builder.collect()) is not None:
                out.append(segment.to_tensordict())
            if deciding:
                n = len(deciding)
                chosen = Decisions(
                    np.zeros((n, 0), np.float32),
                    rng.integers(0, 2, (n, 1)),
                    np.full((n, 1), -0.7, np.float32),
                )
                builder.act(decisions, chosen, policy_version=0)
            alive = [a for a in alive if a not in ending]
    return out


def _steps(kind, agents, ids, rng, group_reward):
    n = len(agents)
    obs = [rng.normal(size=(n, 3)).astype(np.float32)]
    reward = np.full(n, 0.1, np.float32)
    agent_id = np.array([ids[a] for a in agents], np.int32)
    groups = [1 if a <= 3 else 2 for a in agents]
    group_rewards = np.full(n, group_reward, np.float32)
    if kind is DecisionSteps:
        return DecisionSteps(obs, reward, agent_id, None, groups, group_rewards)
    interrupted = np.zeros(n, np.bool_)
    return TerminalSteps(obs, reward, interrupted, agent_id, groups, group_rewards)


def test_absent_places_and_the_order_of_groupmates_change_no_estimate():
    torch.manual_seed(0)
    critic = GroupCritic(SPEC, NET)
    obs = {"vector": torch.randn(5, 3)}
    mates = {"vector": torch.randn(5, 2, 3)}
    action = critic.flat_action(None, torch.randint(0, 2, (5, 2, 1)))
    present = torch.tensor([[True, True], [True, False]] * 2 + [[False, False]])
    value = critic.value(obs, mates, present)
    baseline = critic.baseline(obs, mates, action, present)
    # a third, absent place with garbage in it
    wider = {"vector": torch.cat([mates["vector"], torch.randn(5, 1, 3)], 1)}
    wider_action = torch.cat([action, action[:, :1]], 1)
    wider_present = torch.cat([present, torch.zeros(5, 1, dtype=torch.bool)], 1)
    torch.testing.assert_close(critic.value(obs, wider, wider_present), value)
    torch.testing.assert_close(critic.baseline(obs, wider, wider_action, wider_present), baseline)
    # groupmates in the other order
    swapped = {"vector": mates["vector"].flip(1)}
    both = present.all(1)
    torch.testing.assert_close(critic.value(obs, swapped, present.flip(1))[both], value[both])
    # an absent place's contents never count
    scrambled = {"vector": torch.where(present[..., None], mates["vector"], 9.0)}
    torch.testing.assert_close(critic.value(obs, scrambled, present), value)


def test_the_baseline_depends_on_groupmates_actions_and_not_on_the_agents_own():
    torch.manual_seed(0)
    critic = GroupCritic(SPEC, NET)
    obs = {"vector": torch.randn(4, 3)}
    mates = {"vector": torch.randn(4, 2, 3)}
    present = torch.ones(4, 2, dtype=torch.bool)
    zeros = critic.flat_action(None, torch.zeros(4, 2, 1, dtype=torch.int64))
    ones = critic.flat_action(None, torch.ones(4, 2, 1, dtype=torch.int64))
    assert not torch.allclose(
        critic.baseline(obs, mates, zeros, present), critic.baseline(obs, mates, ones, present)
    )
    assert not torch.allclose(
        critic.value(obs, mates, present), critic.baseline(obs, mates, zeros, present)
    )


def test_an_agent_that_leaves_its_group_bootstraps_from_the_group_and_the_last_do_not():
    store = TrajectoryStore(1000, groupmates=True)
    for batch in group_game(2):
        store.add(batch)
    rows = store.take()
    done = rows.done.nonzero().squeeze(-1)
    early = [r for r in done.tolist() if rows.groupmates["present"][r].any() and r in rows.end_rows]
    # the two leavers of each episode bootstrap (their groups play on), from two mates
    assert len(early) == 4
    ends = rows.end_rows.tolist()
    for row in early:
        at = ends.index(row)
        assert bool(rows.end_groupmates["present"][at].all())
        assert not rows.terminated[row]
    # the others end with their groups: terminated, no bootstrap kept
    assert int(rows.terminated.sum()) == len(done) - 4


def test_the_return_holds_the_agents_its_groups_and_its_groupmates_rewards():
    """With V = 0 and lambda 1 the lambda-return is the discounted sum of the rewards."""
    network = ActorCritic(SPEC, NET)
    poca = POCA(network, settings(gamma=0.5, lambd=1.0, buffer_size=8, batch_size=4))
    with torch.no_grad():
        poca.critic.value_head.weight.zero_()
        poca.critic.value_head.bias.zero_()
    for batch in group_game(1, leave=False):
        poca.add(batch, torch.zeros(len(batch), dtype=torch.int64))
    rows = poca.store.take()
    _, _, returns = poca.estimate_group(rows)
    # each agent: 4 steps of 0.1 own + 2 x 0.1 from its mates, 1.0 group reward at the end
    step = 0.1 + 2 * 0.1
    expected = [step + 0.5 * (step + 0.5 * (step + 0.5 * (step + 1.0))), 0, 0, 0]
    expected[1] = step + 0.5 * (step + 0.5 * (step + 1.0))
    expected[2] = step + 0.5 * (step + 1.0)
    expected[3] = step + 1.0
    first = rows.done.nonzero().squeeze(-1)[0]
    assert int(first) == 3
    torch.testing.assert_close(returns[:4], torch.tensor(expected), rtol=1e-5, atol=1e-6)


def test_an_update_trains_policy_and_critic_and_reports_ml_agents_tags():
    torch.manual_seed(0)
    network = ActorCritic(SPEC, NET)
    poca = POCA(network, settings(buffer_size=32, batch_size=16, learning_rate=1e-2))
    critic_before = [p.detach().clone() for p in poca.critic.parameters()]
    policy_before = network.logits.weight.detach().clone()
    for batch in group_game(4):
        poca.add(batch, torch.zeros(len(batch), dtype=torch.int64))
    assert poca.ready()
    report = poca.update(progress=0.0)
    for tag in (
        "Losses/Policy Loss",
        "Losses/Value Loss",
        "Losses/Baseline Loss",
        "Policy/Extrinsic Value Estimate",
        "Policy/Extrinsic Baseline Estimate",
        "Policy/Entropy",
        "Policy/Learning Rate",
        "Policy/Epsilon",
        "Policy/Beta",
    ):
        assert np.isfinite(report[tag]), tag
    assert report["Losses/Baseline Loss"] > 0 and report["Losses/Value Loss"] > 0
    assert not torch.equal(network.logits.weight, policy_before)
    assert all(
        not torch.equal(p, q) for p, q in zip(poca.critic.parameters(), critic_before, strict=True)
    )
    assert float(poca.critic.most_agents) == 3.0


def test_a_checkpoint_brings_the_group_critic_back():
    torch.manual_seed(0)
    poca = POCA(ActorCritic(SPEC, NET), settings(buffer_size=32, batch_size=16))
    for batch in group_game(4):
        poca.add(batch, torch.zeros(len(batch), dtype=torch.int64))
    poca.update(progress=0.0)
    state = poca.state_dict()
    again = POCA(ActorCritic(SPEC, NET), settings(buffer_size=32, batch_size=16))
    again.load_state_dict(state)
    for name, value in poca.critic.state_dict().items():
        torch.testing.assert_close(again.critic.state_dict()[name], value)
    assert again.optimizer.state_dict()["state"].keys() == state["optimizer"]["state"].keys()


def test_the_group_reward_is_reported_for_the_agents_that_end_with_their_group():
    """ML-Agents' "Environment/Group Cumulative Reward": the leavers' episodes are not
    counted (their group's reward came after they left)."""
    builder = SegmentBuilder("Knights?team=0", SPEC, horizon=16)
    segments = group_game(3, builder=builder)
    np.testing.assert_array_equal(builder.episodes.drain_group(), np.ones(3 * 4))
    ended = builder.episodes.drain()
    assert len(ended.returns) == 3 * 6
    # ML-Agents' "Policy/Extrinsic Reward" of each agent episode adds the group rewards it
    # got (the leavers none) and, under POCA, its groupmates' rewards the learner trains on
    stayed = ended.group_rewards == 1.0
    assert stayed.sum() == 3 * 4 and (ended.group_rewards[~stayed] == 0).all()
    np.testing.assert_allclose(ended.returns[stayed], 0.4, rtol=1e-6)
    np.testing.assert_allclose(ended.returns[~stayed], 0.3, rtol=1e-6)
    mates = sum(float(s[keys.GROUPMATES, keys.REWARD].sum()) for s in segments)
    assert mates > 0 and ended.mates_rewards.sum() == pytest.approx(mates, rel=1e-5)
    assert (ended.mates_rewards[stayed] > ended.mates_rewards[~stayed].max()).all()


def test_groupmates_reach_the_learner_in_the_segments_it_is_sent():
    (batch, *_) = group_game(1)
    assert batch[keys.GROUPMATES, keys.PRESENT].shape[1] == 2


def test_an_agent_alone_in_its_group_is_valued_as_one_whose_groupmates_are_all_absent():
    """A Goalie is alone in its group: the critic takes no groupmates at all (M = 0) and
    values it as it values an agent whose places are all empty."""
    torch.manual_seed(0)
    critic = GroupCritic(SPEC, NET)
    obs = {"vector": torch.randn(5, 3)}
    mates = {"vector": torch.randn(5, 2, 3)}
    action = critic.flat_action(None, torch.randint(0, 2, (5, 2, 1)))
    absent = torch.zeros(5, 2, dtype=torch.bool)
    alone = {"vector": mates["vector"][:, :0]}
    value = critic.value(obs, alone, absent[:, :0])
    baseline = critic.baseline(obs, alone, action[:, :0], absent[:, :0])
    assert value.shape == baseline.shape == (5,)
    torch.testing.assert_close(value, critic.value(obs, mates, absent))
    torch.testing.assert_close(baseline, critic.baseline(obs, mates, action, absent))


@pytest.mark.parametrize("device", DEVICES)
def test_mixed_precision_runs_the_group_critic_in_bfloat16_and_its_head_in_float32(device):
    """The learner's bfloat16 reaches the critic's embeddings, attention and trunk; its
    value head, the values and the losses stay float32, and values stay within bfloat16's
    precision of their float32 form."""
    torch.manual_seed(0)
    network = ActorCritic(SPEC, NET)
    compute = compute_of(device, True)
    compute.place(network)
    mixed = POCA(network, settings(buffer_size=32, batch_size=16), compute)
    critic = mixed.critic
    seen: dict[str, set[torch.dtype]] = {"attention": set(), "trunk": set(), "head": set()}
    critic.attention.q.register_forward_hook(lambda m, i, o: seen["attention"].add(o.dtype))
    critic.trunk[0].register_forward_hook(lambda m, i, o: seen["trunk"].add(o.dtype))
    critic.value_head.register_forward_pre_hook(lambda m, i: seen["head"].add(i[0].dtype))
    obs, mates = {"vector": torch.randn(64, 3)}, {"vector": torch.randn(64, 2, 3)}
    present = torch.rand(64, 2) > 0.3
    on = compute.torch_device
    with torch.no_grad():
        value = critic.value(
            {"vector": obs["vector"].to(on)}, {"vector": mates["vector"].to(on)}, present.to(on)
        ).cpu()
    assert seen == {
        "attention": {torch.bfloat16},
        "trunk": {torch.bfloat16},
        "head": {torch.float32},
    }
    assert value.dtype == torch.float32
    plain = GroupCritic(SPEC, NET)
    plain.load_state_dict(to_cpu(critic.state_dict()))
    with torch.no_grad():
        exact = plain.value(obs, mates, present)
    assert not torch.equal(value, exact)
    torch.testing.assert_close(value, exact, rtol=0.03, atol=0.03 * float(exact.abs().max()))
    for batch in group_game(4):
        mixed.add(batch, torch.zeros(len(batch), dtype=torch.int64))
    report = mixed.update(progress=0.0)
    assert all(np.isfinite(v) for v in report.values())
    assert all(p.grad is None or p.grad.dtype == torch.float32 for p in critic.parameters())
