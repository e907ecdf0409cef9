"""One POCA update, ours and mlagents-learn 1.1.0's own code, on the same buffer and weights.

As ``check_ppo_vs_mlagents.py`` does for PPO: the same initial weights (policy and group
critic), the same rows of groups of three, the minibatches taken in order. The rows hold
every case POCA treats apart: an agent whose group ends with it (group reward, bootstrap
0), an agent that leaves while its groupmates play on (bootstrap from the group's next
observations), rows cut at the horizon, one or two groupmates present from step to step,
groupmates' own rewards. Our side builds the segment as a worker sends it and runs
``learners.algorithms.poca.POCA.update``; ML-Agents' side builds ``AgentExperience`` s with their
``group_status``, a ``Trajectory`` each, and runs its POCA trainer's ``_process_trajectory``
steps (value and baseline estimates, the extrinsic signal with groupmates' rewards,
``lambda_return``) and ``TorchPOCAOptimizer.update``. The weights after the update must
agree to float precision.

    .venv/bin/python -m benchmarks.equality.check_poca_vs_mlagents --seeds 0 1 2
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from benchmarks.equality.common import (
    REPORTED,
    anchor_workarounds,
    load_ours,
    run_sides,
    save_case,
    train_in_order,
    update_in_order,
    vector_spec,
    worst_difference,
    worst_report_difference,
)

BEHAVIOR, OBS_SIZE, BRANCH, MATES = "Knights", 6, 3, 2
ROWS, HORIZON = 24, 16
FIGURES = (*REPORTED, "Losses/Baseline Loss")  # TensorBoard figures compared
GROUP_ENDS, LEAVES, CUT = 0, 1, 2  # how a row ends
CONFIG = {
    "behaviors": {
        BEHAVIOR: {
            "trainer_type": "poca",
            "hyperparameters": {
                "batch_size": 64,
                "buffer_size": 256,
                "learning_rate": 3.0e-3,
                "beta": 0.01,
                "epsilon": 0.2,
                "lambd": 0.95,
                "num_epoch": 3,
                "learning_rate_schedule": "constant",
            },
            "network_settings": {"normalize": False, "hidden_units": 32, "num_layers": 2},
            "reward_signals": {"extrinsic": {"gamma": 0.99, "strength": 1.0}},
            "time_horizon": HORIZON,
        }
    }
}
ACTOR = {"trunk.0": "seq_layers.0", "trunk.2": "seq_layers.2"}
ML_NAMES = {
    **{ours: ("actor", f"network_body._body_endoder.{theirs}") for ours, theirs in ACTOR.items()},
    "logits": ("actor", "action_model._discrete_distribution.branches.0"),
    "critic/obs_embedding.0": (
        "critic",
        "network_body.obs_encoder.self_ent_encoder.seq_layers.0",
    ),
    "critic/obs_action_embedding.0": (
        "critic",
        "network_body.obs_action_encoder.self_ent_encoder.seq_layers.0",
    ),
    **{
        f"critic/attention.{ours}": ("critic", f"network_body.self_attn.fc_{theirs}")
        for ours, theirs in (("q", "q"), ("k", "k"), ("v", "v"), ("out", "out"))
    },
    "critic/trunk.0": ("critic", "network_body.linear_encoder.seq_layers.0"),
    "critic/trunk.2": ("critic", "network_body.linear_encoder.seq_layers.2"),
    "critic/value_head": ("critic", "value_heads.value_heads.extrinsic"),
}


def case(seed: int) -> dict[str, np.ndarray]:
    """Rows of HORIZON steps of agents in groups of three, with their groupmates."""
    rng = np.random.default_rng(seed)
    present = rng.random((ROWS, HORIZON, MATES)) < 0.8
    present[:, :, 0] = True  # at least one groupmate at each step
    ends = np.arange(ROWS) % 3  # GROUP_ENDS, LEAVES, CUT in turn
    present[np.isin(np.arange(ROWS) % 6, (0, 2))] = False  # alone in its group, as a Goalie
    mate_done = np.zeros((ROWS, HORIZON, MATES), bool)
    mate_done[ends == GROUP_ENDS, -1] = True  # the group ends together
    group_reward = np.zeros((ROWS, HORIZON), np.float32)
    group_reward[ends == GROUP_ENDS, -1] = 1.0
    f32 = np.float32
    return {
        "obs": rng.normal(size=(ROWS, HORIZON + 1, OBS_SIZE)).astype(f32),
        "action": rng.integers(0, BRANCH, (ROWS, HORIZON)),
        "reward": rng.normal(0.0, 0.1, (ROWS, HORIZON)).astype(f32),
        "group_reward": group_reward,
        "ends": ends,
        "present": present,
        "mate_obs": rng.normal(size=(ROWS, HORIZON, MATES, OBS_SIZE)).astype(f32)
        * present[..., None],
        "mate_next_obs": rng.normal(size=(ROWS, MATES, OBS_SIZE)).astype(f32)
        * present[:, -1, :, None],
        "mate_action": rng.integers(0, BRANCH, (ROWS, HORIZON, MATES)) * present,
        "mate_reward": rng.normal(0.0, 0.1, (ROWS, HORIZON, MATES)).astype(f32) * present,
        "mate_done": mate_done & present,
    }


def ours(seed: int, out: Path) -> None:
    import torch

    from batches import keys
    from batches.specs import spec_to_dict, step_spec
    from learners.algorithms.poca import POCA
    from learners.networks.policies import ActorCritic
    from learners.trainer_config.parse import parse_config

    settings = parse_config(CONFIG).for_behavior(BEHAVIOR)
    spec = vector_spec(OBS_SIZE, BRANCH)
    torch.manual_seed(seed)
    network = ActorCritic(spec, settings.network_settings)
    poca = POCA(network, settings)
    poca.critic.most_agents.fill_(3.0)  # ML-Agents' grows row by row: start both at the most
    modules = {"": network, "critic/": poca.critic}
    initial = {
        p + k: v.detach().clone().numpy()
        for p, m in modules.items()
        for k, v in m.state_dict().items()
    }
    d = case(seed)
    n, last = ROWS * HORIZON, np.zeros((ROWS, HORIZON), bool)
    last[:, -1] = True
    done = last & (d["ends"] != CUT)[:, None]
    terminated = done  # no interruption here; POCA decides on the groupmates itself

    def flat(array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array.reshape(n, *array.shape[2:])))

    steps = step_spec(spec).expand(n).zero()
    steps[keys.OBS, "v"] = flat(d["obs"][:, :-1])
    steps[keys.NEXT, keys.OBS, "v"] = flat(d["obs"][:, 1:])
    steps[keys.NEXT, keys.REWARD] = flat(d["reward"][..., None])
    steps[keys.NEXT, keys.GROUP_REWARD] = flat(d["group_reward"][..., None])
    steps[keys.NEXT, keys.DONE] = flat((last | done)[..., None])
    steps[keys.NEXT, keys.TERMINATED] = flat(terminated[..., None])
    steps[keys.NEXT, keys.TRUNCATED] = flat((last & ~done)[..., None])
    steps[keys.ACTION, keys.DISCRETE] = flat(d["action"][..., None])
    steps[keys.ACTION_MASK] = torch.ones(n, BRANCH, dtype=torch.bool)
    next_mates = np.zeros_like(d["mate_obs"])
    next_mates[:, :-1] = d["mate_obs"][:, 1:]  # what the next step's groupmates acted on
    next_mates[:, -1] = d["mate_next_obs"]
    steps[keys.GROUPMATES] = {
        keys.OBS: {"v": flat(d["mate_obs"])},
        keys.ACTION: {keys.DISCRETE: flat(d["mate_action"][..., None])},
        keys.REWARD: flat(d["mate_reward"]),
        keys.DONE: flat(d["mate_done"]),
        keys.PRESENT: flat(d["present"]),
    }
    steps[keys.NEXT, keys.GROUPMATES] = {keys.OBS: {"v": flat(next_mates)}}
    with torch.no_grad():  # the acting policy's log-probabilities: the initial weights'
        log_prob, _, _ = network.evaluate(
            {"v": steps[keys.OBS, "v"]}, None, steps[keys.ACTION, keys.DISCRETE]
        )
    steps[keys.LOG_PROB] = log_prob
    steps.set_non_tensor(keys.BEHAVIOR, f"{BEHAVIOR}?team=0")
    steps.set_non_tensor(keys.SPEC, spec_to_dict(spec))
    poca.add(steps, torch.zeros(n, dtype=torch.int64))
    assert poca.ready()
    report = update_in_order(poca)
    after = {
        p + k: v.detach().numpy() for p, m in modules.items() for k, v in m.state_dict().items()
    }
    save_case(out, log_prob.numpy().reshape(ROWS, HORIZON), d, initial, after, report, FIGURES)


def mlagents(case_file: Path, anchor: Path) -> float:
    """ML-Agents' POCA trainer steps and optimizer on the case's rows; returns the worst
    difference from our weights, relative to how far the update moved them."""
    anchor_workarounds(anchor)
    import torch
    from mlagents.plugins.trainer_type import register_trainer_plugins
    from mlagents.trainers.buffer import AgentBuffer, BufferKey, RewardSignalUtil
    from mlagents.trainers.poca.optimizer_torch import TorchPOCAOptimizer
    from mlagents.trainers.policy.torch_policy import TorchPolicy
    from mlagents.trainers.settings import RunOptions
    from mlagents.trainers.torch_entities.action_log_probs import LogProbsTuple
    from mlagents.trainers.torch_entities.networks import SimpleActor
    from mlagents.trainers.trainer.trainer_utils import lambda_return
    from mlagents.trainers.trajectory import AgentExperience, AgentStatus, Trajectory
    from mlagents_envs.base_env import ActionTuple

    register_trainer_plugins()
    d = np.load(case_file)
    settings = RunOptions.from_dict(yaml.safe_load(yaml.safe_dump(CONFIG))).behaviors[BEHAVIOR]
    spec = vector_spec(OBS_SIZE, BRANCH)
    actor = {"conditional_sigma": False, "tanh_squash": False}  # as its POCA trainer
    policy = TorchPolicy(0, spec, settings.network_settings, SimpleActor, actor)
    optimizer = TorchPOCAOptimizer(policy, settings)
    modules = {"actor": policy.actor, "critic": optimizer.critic}
    load_ours(modules, ML_NAMES, d)
    state = optimizer.critic.state_dict()
    state["network_body._current_max_agents"] = torch.tensor(3.0)
    optimizer.critic.load_state_dict(state)

    def act(a: int) -> ActionTuple:
        return ActionTuple(continuous=np.zeros(0, np.float32), discrete=np.array([a]))

    extrinsic, h = optimizer.reward_signals["extrinsic"], settings.hyperparameters
    update = AgentBuffer()
    for row in range(ROWS):  # one trajectory per row, as its trainer's _process_trajectory
        ends = int(d["ends"][row])
        experiences = []
        for t in range(HORIZON):
            mates = [
                AgentStatus(
                    obs=[d["mate_obs"][row, t, m]],
                    reward=float(d["mate_reward"][row, t, m]),
                    action=act(int(d["mate_action"][row, t, m])),
                    done=bool(d["mate_done"][row, t, m]),
                )
                for m in range(MATES)
                if d["present"][row, t, m]
            ]
            experiences.append(
                AgentExperience(
                    obs=[d["obs"][row, t]],
                    reward=float(d["reward"][row, t]),
                    done=ends != CUT and t == HORIZON - 1,
                    action=act(int(d["action"][row, t])),
                    action_probs=LogProbsTuple(
                        continuous=np.zeros(0, np.float32),
                        discrete=d["log_prob"][row, t : t + 1],
                    ),
                    action_mask=[np.zeros(BRANCH, bool)],  # ML-Agents: True = masked
                    prev_action=np.zeros(1, np.int32),
                    interrupted=False,
                    memory=None,
                    group_status=mates,
                    group_reward=float(d["group_reward"][row, t]),
                )
            )
        next_mates = [
            [d["mate_next_obs"][row, m]] for m in range(MATES) if d["present"][row, -1, m]
        ]
        trajectory = Trajectory(
            experiences, [d["obs"][row, HORIZON]], next_mates, str(row), BEHAVIOR
        )
        buffer = trajectory.to_agentbuffer()
        value, baseline, value_next, _, _ = optimizer.get_trajectory_and_baseline_value_estimates(
            buffer,
            trajectory.next_obs,
            trajectory.next_group_obs,
            trajectory.all_group_dones_reached
            and trajectory.done_reached
            and not trajectory.interrupted,
        )
        buffer[RewardSignalUtil.value_estimates_key("extrinsic")].extend(value["extrinsic"])
        buffer[RewardSignalUtil.baseline_estimates_key("extrinsic")].extend(baseline["extrinsic"])
        returns = lambda_return(
            r=extrinsic.evaluate(buffer) * extrinsic.strength,
            value_estimates=value["extrinsic"],
            gamma=extrinsic.gamma,
            lambd=h.lambd,
            value_next=value_next["extrinsic"],
        )
        advantage = np.array(returns) - np.array(baseline["extrinsic"])
        buffer[RewardSignalUtil.returns_key("extrinsic")].set(returns)
        buffer[RewardSignalUtil.advantage_key("extrinsic")].set(advantage)
        buffer[BufferKey.ADVANTAGES].set(list(advantage))
        buffer.resequence_and_append(update, training_length=policy.sequence_length)
    figures = train_in_order(update, optimizer, h)
    return max(worst_difference(modules, ML_NAMES, d), worst_report_difference(figures, d, FIGURES))


if __name__ == "__main__":
    run_sides(__spec__.name, ours, mlagents, __doc__)
