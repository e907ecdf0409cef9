"""``network_settings.memory``: the config, the LSTM acting in numpy as in torch, sequences,
the critic's memory along an agent's pieces, and PPO learning what only memory solves."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from mlagents_envs.base_env import BehaviorSpec

from batches import keys
from learners.acting.numpy_policy import NumpyActor
from learners.algorithms.ppo import PPO
from learners.algorithms.recurrent_ppo import RecurrentPPO, SequenceInputs, sequences
from learners.networks.policies import ActorCritic, numpy_state
from learners.trainer_config.parse import ConfigError, load_config
from learners.trainer_config.settings import (
    Hyperparameters,
    MemorySettings,
    NetworkSettings,
    TrainerSettings,
)
from testkit.segments import segment, vector_spec

ANCHORS = Path(__file__).resolve().parents[3] / "shared" / "anchors" / "mlagents-configs"


def write(tmp_path: Path, network: str, trainer: str = "ppo") -> Path:
    path = tmp_path / "config.yaml"
    path.write_text(
        f"behaviors:\n  Hallway:\n    trainer_type: {trainer}\n    network_settings:\n{network}"
    )
    return path


def test_the_config_reads_memory_with_mlagents_defaults(tmp_path):
    config = load_config(write(tmp_path, "      memory:\n        memory_size: 32\n"))
    memory = config.behaviors["Hallway"].network_settings.memory
    assert memory == MemorySettings(memory_size=32, sequence_length=64)
    assert config.unsupported == ()
    config = load_config(write(tmp_path, "      memory:\n"))  # an empty section: none
    assert config.behaviors["Hallway"].network_settings.memory is None


@pytest.mark.parametrize(
    ("network", "message"),
    [
        ("      memory:\n        memory_size: 33\n", "memory.memory_size: expected an even number"),
        ("      memory:\n        sequence_length: 0\n", "memory.sequence_length: expected a posi"),
        ("      memory:\n        memory_sise: 8\n", "did you mean 'memory_size'?"),
    ],
)
def test_a_bad_memory_is_one_line(tmp_path, network, message):
    with pytest.raises(ConfigError, match=message) as error:
        load_config(write(tmp_path, network))
    assert "\n" not in str(error.value)


def test_memory_under_a_trainer_without_it_is_reported(tmp_path):
    config = load_config(write(tmp_path, "      memory:\n        memory_size: 32\n", "impala"))
    assert config.unsupported == ("behaviors.Hallway.network_settings.memory",)
    assert config.behaviors["Hallway"].network_settings.memory is None


@pytest.mark.skipif(not ANCHORS.is_dir(), reason="ML-Agents' configs are not beside the repo")
def test_mlagents_ppo_hallway_config_runs_with_memory():
    config = load_config(ANCHORS / "ppo" / "Hallway.yaml")
    assert config.unsupported == ()
    assert config.behaviors["Hallway"].network_settings.memory == MemorySettings(128, 64)


def memory_network(spec: BehaviorSpec, size: int = 16, length: int = 4, **kw) -> ActorCritic:
    settings = NetworkSettings(hidden_units=16, memory=MemorySettings(size, length), **kw)
    torch.manual_seed(0)
    return ActorCritic(spec, settings)


@pytest.mark.parametrize("actions", [(0, (3, 2)), (2, ())], ids=["discrete", "continuous"])
def test_the_numpy_lstm_acts_as_torchs(actions):
    spec = vector_spec(6, actions[0], actions[1])
    network = memory_network(spec, deterministic=True)
    for p in network.parameters():  # away from the initial weights' zeros
        p.data.add_(0.1 * torch.randn_like(p))
    actor = NumpyActor(spec, network.settings, numpy_state(network))
    assert actor.memory_size == network.memory_size == 16
    rng = np.random.default_rng(0)
    memory_np = memory_torch = None
    for _ in range(3):
        obs = {"vector": rng.normal(size=(5, 6)).astype(np.float32)}
        *acted_np, memory_np = actor.act_recurrent(obs, None, memory_np)
        *acted, memory_torch = network.act_recurrent(
            {"vector": torch.from_numpy(obs["vector"])}, None, memory_torch, True
        )
        for mine, theirs in zip(acted_np, acted, strict=True):
            np.testing.assert_allclose(mine, theirs.numpy(), atol=1e-5)
        np.testing.assert_allclose(memory_np, memory_torch.numpy(), atol=1e-5)
    assert np.abs(memory_np).max() > 0.01


def test_pieces_are_cut_into_sequences_padded_at_their_end():
    done = torch.tensor([0, 0, 0, 0, 1, 0, 0, 1], dtype=torch.bool)  # pieces of 5 and 3
    seqs = sequences(done, 2)
    assert seqs.rows.tolist() == [[0, 1], [2, 3], [4, 4], [5, 6], [7, 7]]
    assert seqs.valid.tolist() == [[1, 1], [1, 1], [1, 0], [1, 1], [1, 0]]
    assert seqs.piece.tolist() == [0, 0, 0, 1, 1] and seqs.chunk.tolist() == [0, 1, 2, 0, 1]


def trajectory(network: ActorCritic, steps: int, seed: int = 0) -> tuple[list, torch.Tensor]:
    """One agent's steps as acted (observations, the memory each read), from an episode's start."""
    torch.manual_seed(seed)
    obs = [torch.randn(1, 4) for _ in range(steps + 1)]
    memories, memory = [], torch.zeros(1, network.memory_size)
    for step in range(steps):
        memories.append(memory)
        memory = network.act_recurrent({"vector": obs[step]}, None, memory)[3]
    return obs, torch.cat(memories)


def pieces(
    spec: BehaviorSpec, obs: list, memories: torch.Tensor, start: int, stop: int, agent: int = 7
):
    """Steps ``start:stop`` of the trajectory as one worker piece, cut there (truncated)."""
    piece = segment(spec, 1, stop - start)
    piece[keys.OBS, "vector"] = torch.cat(obs[start:stop])
    piece[keys.NEXT, keys.OBS, "vector"] = torch.cat(obs[start + 1 : stop + 1])
    piece[keys.MEMORY] = memories[start:stop]
    piece[keys.AGENT_ID] = torch.full((stop - start,), agent)
    piece[keys.WORKER] = torch.zeros(stop - start, dtype=torch.int64)
    return piece


def ppo(network: ActorCritic, buffer_size: int = 8, **hyper) -> RecurrentPPO:
    h = Hyperparameters(buffer_size=buffer_size, batch_size=8, **hyper)
    settings = TrainerSettings(hyperparameters=h, network_settings=network.settings)
    return RecurrentPPO(network, settings)


def test_the_critic_runs_along_an_agents_pieces_across_updates():
    """An agent's 12 steps valued as one piece, as three pieces in one update, and as three
    pieces in three updates: the critic's memory runs on, so the values agree."""
    spec = vector_spec(4, 0, (2,))
    network = memory_network(spec)
    obs, memories = trajectory(network, 12)
    whole = ppo(network)
    whole.store.add(pieces(spec, obs, memories, 0, 12))
    expected = whole.value_estimates(whole.store.take())[0]
    split = ppo(network)
    for start in (0, 4, 8):
        split.store.add(pieces(spec, obs, memories, start, start + 4))
    torch.testing.assert_close(split.value_estimates(split.store.take())[0], expected)
    apart = ppo(network)
    got = []
    for start in (0, 4, 8):
        apart.store.add(pieces(spec, obs, memories, start, start + 4))
        got.append(apart.value_estimates(apart.store.take())[0])
    torch.testing.assert_close(torch.cat(got), expected)
    # another agent's piece, or an episode's first (actor memory zeros), starts from zeros
    fresh = ppo(network)
    fresh.store.add(pieces(spec, obs, memories, 0, 4))
    fresh.value_estimates(fresh.store.take())
    fresh.store.add(pieces(spec, obs, memories, 4, 8, agent=8))
    other = fresh.value_estimates(fresh.store.take())[0]
    alone = ppo(network)
    alone.store.add(pieces(spec, obs, memories, 4, 8, agent=8))
    torch.testing.assert_close(other, alone.value_estimates(alone.store.take())[0])
    assert not torch.allclose(other, expected[4:8])


def test_padding_counts_as_mlagents_update_buffer_counts_it():
    """Pieces of 5 and 1 steps in sequences of 4 take 8 + 4 places in ML-Agents' update
    buffer, which its trainer counts against ``buffer_size``: ready after 6 steps, where
    PPO without memory waits for more than 8. The next buffer counts from nothing."""
    spec = vector_spec(4, 0, (2,))
    network = memory_network(spec, length=4)
    obs, memories = trajectory(network, 6)
    learner = ppo(network, buffer_size=8)
    learner.add(pieces(spec, obs, memories, 0, 5), torch.zeros(5, dtype=torch.int64))
    assert (learner.buffered(), learner.ready(), learner.wanted()) == (8, False, 1)  # 1 place
    learner.add(pieces(spec, obs, memories, 5, 6), torch.zeros(1, dtype=torch.int64))
    assert (learner.buffered(), learner.ready()) == (12, True)
    learner.update(0.0)
    # workers count steps: 9 places are 5 steps where 6 steps took 12 places so far
    assert (learner.buffered(), learner.wanted()) == (0, 5)


def test_advantages_are_normalized_over_the_padded_sequences_as_in_mlagents():
    """ML-Agents' ``_update_policy`` normalizes its update buffer's advantages, the
    padding's zeros among them: pieces of 5 and 3 steps in sequences of 4 add 3 + 1
    zeros to the mean and the std."""
    network = memory_network(vector_spec(4, 0, (2,)), length=4)
    learner = ppo(network)
    done = torch.tensor([0, 0, 0, 0, 1, 0, 0, 1], dtype=torch.bool)
    memory = torch.zeros(3, network.memory_size)
    learner._inputs = SequenceInputs(
        sequences(done, 4), memory, memory, torch.ones(8, dtype=torch.bool)
    )
    advantage = torch.linspace(-1.0, 2.0, 8)
    padded = np.concatenate([advantage.numpy(), np.zeros(4, np.float32)])
    expected = (advantage.numpy() - padded.mean()) / (padded.std() + 1e-10)
    got = learner.normalized(advantage, torch.arange(8))
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-5)
    assert abs(float(got.mean())) > 0.1  # the real steps' mean is not 0


# ---- learning: recall a cue shown only at an episode's first step ---------------------


CUE_STEPS = 4  # the cue at step 0, blanks, then the choice at the last step


def recall_episodes(network: ActorCritic, agents: int, version: int, rng: torch.Generator):
    """``agents`` episodes of the recall task acted by ``network`` (from zero memories),
    packed as a worker packs them; the share of right choices."""
    spec_steps = agents * CUE_STEPS
    cue = torch.randint(0, 2, (agents,), generator=rng)
    obs = torch.zeros(agents, CUE_STEPS + 1, 3)
    obs[:, 0, 0] = cue * 2.0 - 1.0
    obs[torch.arange(agents), :, 1] = torch.linspace(0, 1, CUE_STEPS + 1)
    obs[:, CUE_STEPS - 1, 2] = 1.0  # "choose now"
    memory = torch.zeros(agents, network.memory_size)
    acted, memories, log_probs = [], [], []
    for step in range(CUE_STEPS):
        memories.append(memory)
        _, discrete, log_prob, after = network.act_recurrent({"vector": obs[:, step]}, None, memory)
        memory = memory if after is None else after
        acted.append(discrete)
        log_probs.append(log_prob)
    choice = acted[-1][:, 0]
    reward = torch.zeros(agents, CUE_STEPS)
    reward[:, -1] = (choice == cue).float()
    batch = segment(vector_spec(3, 0, (2,)), agents, CUE_STEPS)
    batch[keys.OBS, "vector"] = obs[:, :CUE_STEPS].reshape(spec_steps, 3)
    batch[keys.NEXT, keys.OBS, "vector"] = obs[:, 1:].reshape(spec_steps, 3)
    batch[keys.ACTION, keys.DISCRETE] = torch.stack(acted, 1).reshape(spec_steps, 1)
    batch[keys.LOG_PROB] = torch.stack(log_probs, 1).reshape(spec_steps, 1)
    if network.memory_size:
        batch[keys.MEMORY] = torch.stack(memories, 1).reshape(spec_steps, -1)
    batch[keys.NEXT, keys.REWARD] = reward.reshape(spec_steps, 1)
    batch[keys.NEXT, keys.TERMINATED] = batch[keys.NEXT, keys.DONE].clone()
    batch[keys.NEXT, keys.TRUNCATED] = torch.zeros(spec_steps, 1, dtype=torch.bool)
    batch[keys.AGENT_ID] = torch.arange(agents).repeat_interleave(CUE_STEPS) + version * agents
    batch[keys.WORKER] = torch.zeros(spec_steps, dtype=torch.int64)
    batch[keys.POLICY_VERSION] = torch.full((spec_steps,), version)
    return batch, float((choice == cue).float().mean())


def learn_recall(network: ActorCritic, learner: Any, batches: int) -> list[float]:
    """``learner``: PPO's or SAC's (tests/learners/test_recurrent_sac.py)."""
    rng = torch.Generator().manual_seed(1)
    scores: list[float] = []
    for version in range(batches):
        batch, score = recall_episodes(network, 128, version, rng)
        scores.append(score)
        learner.add(batch, torch.zeros(len(batch), dtype=torch.int64))
        if learner.ready():
            learner.update(progress=0.0)
        if np.mean(scores[-3:]) > 0.95:
            break
    return scores


def test_ppo_with_memory_learns_to_recall_a_cue():
    """Only the first step shows the cue; the last asks for it. Without memory the best
    policy is right half the time; with it PPO gets near every choice right."""
    spec = vector_spec(3, 0, (2,))
    network = memory_network(spec, size=32, length=CUE_STEPS)
    scores = learn_recall(network, ppo(network, 511, learning_rate=3e-3, beta=1e-3), 60)
    assert np.mean(scores[-3:]) > 0.95, scores
    torch.manual_seed(0)
    plain = ActorCritic(spec, NetworkSettings(hidden_units=16))
    h = Hyperparameters(buffer_size=511, batch_size=64, learning_rate=3e-3, beta=1e-3)
    control = PPO(plain, TrainerSettings(hyperparameters=h, network_settings=plain.settings))
    scores = learn_recall(plain, control, 20)
    assert np.mean(scores[-5:]) < 0.65, scores


@pytest.mark.parametrize("squashed", [False, True], ids=["ppo", "sac"])
def test_the_onnx_export_carries_the_memory_in_and_out(tmp_path, squashed):
    """ML-Agents' layout: ``recurrent_in`` [batch, 1, memory_size] last in, ``recurrent_out``
    last out, ``memory_size`` its size; three steps in onnxruntime act as the network (PPO's
    policy, and SAC's, squashed with a log-std head)."""
    import onnx
    import onnxruntime as ort

    from learners.host.export import export_onnx

    spec = vector_spec(6, 2, (3,))
    network = memory_network(spec, tanh_squash=squashed, conditional_sigma=squashed)
    for p in network.parameters():
        p.data.add_(0.1 * torch.randn_like(p))
    path = export_onnx(network, tmp_path / "Hallway.onnx")
    model = onnx.load(str(path))
    assert [i.name for i in model.graph.input] == ["obs_0", "action_masks", "recurrent_in"]
    assert [o.name for o in model.graph.output][-1] == "recurrent_out"
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [o.name for o in sess.get_outputs()]
    rng = np.random.default_rng(0)
    memory, mine = np.zeros((5, 1, 16), np.float32), None
    for _ in range(3):
        obs = rng.normal(size=(5, 6)).astype(np.float32)
        feed = {"obs_0": obs, "action_masks": np.ones((5, 3), np.float32), "recurrent_in": memory}
        out = dict(zip(names, sess.run(None, feed), strict=True))
        assert out["memory_size"].tolist() == [16.0]
        continuous, discrete, _, mine = network.act_recurrent(
            {"vector": torch.from_numpy(obs)}, None, mine, True
        )
        np.testing.assert_allclose(
            out["deterministic_continuous_actions"],
            network.unity_action(continuous).numpy(),
            atol=1e-5,
        )
        np.testing.assert_array_equal(out["deterministic_discrete_actions"], discrete.numpy())
        np.testing.assert_allclose(out["recurrent_out"][:, 0], mine.numpy(), atol=1e-5)
        memory = out["recurrent_out"]


def test_record_demo_acts_with_each_agents_memory():
    """``record-demo --checkpoint`` with a policy with memory acts as a worker does: from
    the agent's memory of its last decision, from zeros again after its episode ended."""
    from mlagents_envs.base_env import DecisionSteps

    from driver.recording.recorder import PolicyActor

    spec = vector_spec(6, 0, (3,))
    network = memory_network(spec)
    for p in network.parameters():
        p.data.add_(0.3 * torch.randn_like(p))
    actor = PolicyActor(network, stochastic=False)
    obs = np.random.default_rng(0).normal(size=(2, 6)).astype(np.float32)

    def step() -> None:
        ids = np.array([3, 4], np.int32)
        steps = DecisionSteps(
            [obs],
            np.zeros(2, np.float32),
            ids,
            None,
            np.zeros(2, np.int32),
            np.zeros(2, np.float32),
        )
        actor.act(steps)

    step()
    assert actor.memories is not None and len(actor.memories) == 2
    first = actor.memories.get(np.array([3, 4]))
    step()
    second = actor.memories.get(np.array([3, 4]))
    assert not np.allclose(first, second)  # the second decision read the first's memory
    actor.ended([3])
    np.testing.assert_array_equal(actor.memories.get(np.array([3])), 0.0)
    step()
    np.testing.assert_allclose(actor.memories.get(np.array([3])), first[:1], atol=1e-6)


def test_agent_memories_are_bounded_and_forgotten():
    from driver.recording.recorder import AgentMemories

    memories = AgentMemories(2, kept=3)
    memories.put(np.array([1, 2, 3]), np.ones((3, 2), np.float32))
    memories.put(np.array([1]), np.full((1, 2), 2.0, np.float32))  # 1 is the most recent
    memories.put(np.array([4]), np.ones((1, 2), np.float32))  # 2, the least recent, goes
    assert len(memories) == 3
    np.testing.assert_array_equal(memories.get(np.array([2, 1])), [[0, 0], [2, 2]])
    memories.forget(np.array([1]))
    np.testing.assert_array_equal(memories.get(np.array([1])), [[0, 0]])


def test_the_learner_trains_memory_with_reward_signals(tmp_path):
    """A behavior with memory and an intrinsic signal: RecurrentPPO, the signal's value head
    on the critic's LSTM."""
    from learners.host.learner import CentralLearner
    from learners.trainer_config.parse import load_config

    path = write(tmp_path, "      memory:\n        memory_size: 16\n        sequence_length: 4\n")
    text = path.read_text() + (
        "    hyperparameters: {buffer_size: 64, batch_size: 16}\n"
        "    reward_signals:\n      extrinsic: {gamma: 0.99}\n      rnd: {strength: 0.01}\n"
    )
    path.write_text(text)
    learner = CentralLearner(load_config(path))
    spec = vector_spec(4, 0, (2,))
    batch = segment(spec, 20, 4, behavior="Hallway?team=0")
    batch[keys.MEMORY] = torch.zeros(80, 16)
    learner.submit([batch])
    (state,) = learner.behaviors.values()
    assert isinstance(state.algorithm, RecurrentPPO) and state.updates
    (_, _, report), *_ = learner.drain_reports()
    assert "Policy/Rnd Value Estimate" in report and report["Losses/Value Loss"] >= 0
