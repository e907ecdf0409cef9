"""One PPO update with memory, ours and mlagents-learn 1.1.0's own code, on the same steps.

As ``check_ppo_vs_mlagents.py`` does without memory: the same initial weights (actor and
critic, each with its LSTM), the same steps, the minibatches taken in order. One agent's
trajectories follow each other as its trainer receives them: pieces cut at
``time_horizon`` while the episode goes on (the actor's memory and the critic's run on
into the next piece), episodes that end before it (a short piece, padded at its end,
then a new episode from zero memory), and a last episode interrupted (bootstrapped).
Pieces are cut into sequences of ``sequence_length`` that do not divide them, so most
end in padding. Our actor acts along the trajectories step by step and gives each step
the memory its decision read and its log-probabilities; both sides take those.

Our side runs ``learners.algorithms.recurrent_ppo.RecurrentPPO.update``. ML-Agents' side builds an
``AgentExperience`` per step (with its memory), a ``Trajectory`` per piece, and runs its
PPO trainer's ``_process_trajectory`` steps (the critic's values and memories by
sequence from the memory the previous piece left, ``get_gae``), ``resequence_and_append``
and its ``_update_policy``: the whole-buffer advantage normalization, then ``num_epoch``
passes of ``TorchPPOOptimizer.update`` on ``batch_size // sequence_length`` sequences.
The weights after the update must agree to float precision.

    .venv/bin/python -m benchmarks.equality.check_recurrent_ppo_vs_mlagents --seeds 0 1 2
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.equality.common import (
    REPORTED,
    anchor_workarounds,
    load_ours,
    mlagents_ppo,
    reported,
    run_sides,
    train_in_order,
    update_in_order,
    vector_spec,
    worst_difference,
    worst_report_difference,
)

BEHAVIOR, OBS_SIZE, BRANCH = "Hallway", 8, 5  # Hallway's five moves
HORIZON, LENGTH, PIECES = 40, 16, 14  # time_horizon, sequence_length, pieces in the case
CUT, ENDS, INTERRUPTED = 0, 1, 2  # how a piece ends
CONFIG = {  # ML-Agents' ppo/Hallway.yaml, smaller, with a sequence length that cuts pieces
    "behaviors": {
        BEHAVIOR: {
            "trainer_type": "ppo",
            "hyperparameters": {
                "batch_size": 4 * LENGTH,
                "buffer_size": 256,
                "learning_rate": 3.0e-3,
                "beta": 0.03,
                "epsilon": 0.2,
                "lambd": 0.95,
                "num_epoch": 3,
                "learning_rate_schedule": "constant",
            },
            "network_settings": {
                "normalize": False,
                "hidden_units": 32,
                "num_layers": 2,
                "memory": {"memory_size": 32, "sequence_length": LENGTH},
            },
            "reward_signals": {"extrinsic": {"gamma": 0.99, "strength": 1.0}},
            "time_horizon": HORIZON,
        }
    }
}
ACTOR_NAMES = {
    "trunk.0": "network_body._body_endoder.seq_layers.0",
    "trunk.2": "network_body._body_endoder.seq_layers.2",
    "lstm": "network_body.lstm.lstm",
}
ML_NAMES = {
    **{ours: ("actor", theirs) for ours, theirs in ACTOR_NAMES.items()},
    **{f"critic_{ours}": ("critic", theirs) for ours, theirs in ACTOR_NAMES.items()},
    "logits": ("actor", "action_model._discrete_distribution.branches.0"),
    "value": ("critic", "value_heads.value_heads.extrinsic"),
}


def pieces(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Each piece's length and how it ends: mostly cut at the horizon, an episode ending
    early every few pieces, the last one interrupted."""
    rng = np.random.default_rng(seed)
    ends = np.where(rng.random(PIECES) < 0.35, ENDS, CUT)
    ends[-1] = INTERRUPTED
    lengths = np.where(ends == ENDS, rng.integers(3, HORIZON, PIECES), HORIZON)
    return lengths, ends


def ours(seed: int, out: Path) -> None:
    import torch

    from batches import keys
    from batches.specs import spec_to_dict, step_spec
    from learners.algorithms.recurrent_ppo import RecurrentPPO
    from learners.networks.policies import ActorCritic
    from learners.trainer_config.parse import parse_config

    settings = parse_config(CONFIG).for_behavior(BEHAVIOR)
    spec = vector_spec(OBS_SIZE, BRANCH)
    torch.manual_seed(seed)
    network = ActorCritic(spec, settings.network_settings)
    initial = {k: v.detach().clone().numpy() for k, v in network.state_dict().items()}
    lengths, ends = pieces(seed)
    rng = np.random.default_rng(seed + 1000)
    n, size = int(lengths.sum()), network.memory_size
    obs = np.zeros((n, OBS_SIZE), np.float32)
    next_obs = np.zeros_like(obs)
    reward = rng.normal(0.0, 0.05, n).astype(np.float32)
    memory = np.zeros((n, size), np.float32)
    action = np.zeros((n, 1), np.int64)
    log_prob = np.zeros((n, 1), np.float32)
    last = np.zeros(n, bool)
    terminated = np.zeros(n, bool)
    at, state, seen = 0, None, rng.normal(size=OBS_SIZE).astype(np.float32)
    for length, end in zip(lengths.tolist(), ends.tolist(), strict=True):
        for t in range(length):  # the actor steps along the piece from the memory it has
            obs[at + t] = seen
            memory[at + t] = 0.0 if state is None else state.numpy()[0]
            x = {"v": torch.from_numpy(seen[None])}
            _, discrete, logp, state = network.act_recurrent(x, None, state)
            action[at + t], log_prob[at + t] = discrete.numpy()[0], logp.numpy()[0]
            seen = rng.normal(size=OBS_SIZE).astype(np.float32)
            next_obs[at + t] = seen
        at += length
        last[at - 1] = True
        if end == ENDS:
            terminated[at - 1] = True
            reward[at - 1] = 1.0 if rng.random() < 0.5 else -0.1  # the right goal, or not
        if end != CUT:  # a new episode: zero memory, a fresh first observation
            state, seen = None, rng.normal(size=OBS_SIZE).astype(np.float32)

    def tensor(array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(array)

    steps = step_spec(spec).expand(n).zero()
    steps[keys.OBS, "v"] = tensor(obs)
    steps[keys.NEXT, keys.OBS, "v"] = tensor(next_obs)
    steps[keys.NEXT, keys.REWARD] = tensor(reward[:, None])
    steps[keys.NEXT, keys.DONE] = tensor(last[:, None])
    steps[keys.NEXT, keys.TERMINATED] = tensor(terminated[:, None])
    steps[keys.NEXT, keys.TRUNCATED] = tensor((last & ~terminated)[:, None])
    steps[keys.ACTION, keys.DISCRETE] = tensor(action)
    steps[keys.ACTION_MASK] = torch.ones(n, BRANCH, dtype=torch.bool)
    steps[keys.LOG_PROB] = tensor(log_prob)
    steps[keys.AGENT_ID] = torch.zeros(n, dtype=torch.int64)
    steps[keys.MEMORY] = tensor(memory)
    steps.set_non_tensor(keys.BEHAVIOR, f"{BEHAVIOR}?team=0")
    steps.set_non_tensor(keys.SPEC, spec_to_dict(spec))
    ppo = RecurrentPPO(network, settings)
    ppo.add(steps, torch.zeros(n, dtype=torch.int64))
    report = update_in_order(ppo)
    after = {k: v.detach().numpy() for k, v in network.state_dict().items()}
    np.savez(
        out,
        lengths=lengths,
        ends=ends,
        obs=obs,
        next_obs=next_obs,
        reward=reward,
        memory=memory,
        action=action,
        log_prob=log_prob,
        **{f"initial/{k}": v for k, v in initial.items()},
        **{f"after/{k}": v for k, v in after.items()},
        **reported(report, REPORTED),
    )


def mlagents(case_file: Path, anchor: Path) -> float:
    """ML-Agents' PPO trainer steps and optimizer on the case's pieces; returns the worst
    difference from our weights, relative to how far the update moved them."""
    anchor_workarounds(anchor)
    from mlagents.trainers.buffer import AgentBuffer, BufferKey, RewardSignalUtil
    from mlagents.trainers.torch_entities.action_log_probs import LogProbsTuple
    from mlagents.trainers.trainer.trainer_utils import get_gae
    from mlagents.trainers.trajectory import AgentExperience, Trajectory
    from mlagents_envs.base_env import ActionTuple

    d = np.load(case_file)
    policy, optimizer, settings = mlagents_ppo(CONFIG, BEHAVIOR, vector_spec(OBS_SIZE, BRANCH))
    modules = {"actor": policy.actor, "critic": optimizer.critic}
    load_ours(modules, ML_NAMES, d)
    extrinsic, h = optimizer.reward_signals["extrinsic"], settings.hyperparameters
    update, at = AgentBuffer(), 0
    for length, end in zip(d["lengths"].tolist(), d["ends"].tolist(), strict=True):
        experiences = [
            AgentExperience(
                obs=[d["obs"][t]],
                reward=float(d["reward"][t]),
                done=end != CUT and t == at + length - 1,
                action=ActionTuple(np.zeros(0, np.float32), d["action"][t].astype(np.int32)),
                action_probs=LogProbsTuple(np.zeros(0, np.float32), d["log_prob"][t]),
                action_mask=[np.zeros(BRANCH, bool)],  # ML-Agents: True = masked
                prev_action=np.zeros(1, np.int32),
                interrupted=end == INTERRUPTED and t == at + length - 1,
                memory=d["memory"][t],
                group_status=[],
                group_reward=0.0,
            )
            for t in range(at, at + length)
        ]
        at += length
        trajectory = Trajectory(experiences, [d["next_obs"][at - 1]], [], "0", BEHAVIOR)
        buffer = trajectory.to_agentbuffer()
        values, value_next, critic_memories = optimizer.get_trajectory_value_estimates(
            buffer, trajectory.next_obs, trajectory.done_reached and not trajectory.interrupted
        )  # as its PPO trainer calls it
        buffer[BufferKey.CRITIC_MEMORY].set(critic_memories)
        buffer[RewardSignalUtil.value_estimates_key("extrinsic")].extend(values["extrinsic"])
        advantage = get_gae(
            rewards=extrinsic.evaluate(buffer) * extrinsic.strength,
            value_estimates=values["extrinsic"],
            value_next=value_next["extrinsic"],
            gamma=extrinsic.gamma,
            lambd=h.lambd,
        )
        buffer[RewardSignalUtil.returns_key("extrinsic")].set(advantage + values["extrinsic"])
        buffer[RewardSignalUtil.advantage_key("extrinsic")].set(advantage)
        buffer[BufferKey.ADVANTAGES].set(list(advantage))
        buffer.resequence_and_append(update, training_length=policy.sequence_length)
    figures = train_in_order(update, optimizer, h, policy.sequence_length)
    return max(
        worst_difference(modules, ML_NAMES, d), worst_report_difference(figures, d, REPORTED)
    )


if __name__ == "__main__":
    run_sides(__spec__.name, ours, mlagents, __doc__)
