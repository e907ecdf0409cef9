"""One PPO update on several discrete branches with action masks, ours and mlagents-learn
1.1.0's own code, on the same buffer and weights (``check_ppo_vs_mlagents.py`` checks one
branch without masks).

WallJump's action space: branches (3, 3, 3, 2), the last one's second action (jump)
masked on a third of the steps, as a build masks jumping in the air. The minibatches are
taken in order; the weights after the update must agree to float precision.

ML-Agents' PPO computes its value loss with ``trust_region_value_loss`` (the value clipped
to ``epsilon`` around the stored estimate), but in mlagents 1.1.0
``RewardSignalUtil.value_estimates_key`` returns the returns' key: the stored "estimate" is
the lambda-return itself, so the clipped term is never the larger and the loss is the plain
squared error, as ours (a clipped loss differs here by up to 9e-2).

    .venv/bin/python -m benchmarks.equality.check_ppo_branches_vs_mlagents --seeds 0 1 2
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.equality.common import (
    CONFIG,
    REPORTED,
    ROWS,
    anchor_workarounds,
    mlagents_update,
    packed_steps,
    run_sides,
    save_case,
    update_in_order,
    worst_report_difference,
)

BEHAVIOR, OBS_SIZE, BRANCHES = "Basic", 20, (3, 3, 3, 2)
ML_NAMES = {
    "trunk.0": ("actor", "network_body._body_endoder.seq_layers.0"),
    "critic_trunk.0": ("critic", "network_body._body_endoder.seq_layers.0"),
    "value": ("critic", "value_heads.value_heads.extrinsic"),
}
ML_BRANCH = "action_model._discrete_distribution.branches.{}"


def branch_spec() -> Any:
    from mlagents_envs.base_env import (
        ActionSpec,
        BehaviorSpec,
        DimensionProperty,
        ObservationSpec,
        ObservationType,
    )

    sensor = ObservationSpec((OBS_SIZE,), (DimensionProperty.NONE,), ObservationType.DEFAULT, "v")
    return BehaviorSpec([sensor], ActionSpec(0, BRANCHES))


def buffer(seed: int, horizon: int) -> dict[str, np.ndarray]:
    """As ``check_ppo_vs_mlagents.buffer``, with an action per branch and the jump masked
    (and not taken) on a third of the steps; ``allowed``: True = allowed."""
    rng = np.random.default_rng(seed)
    reward = np.full((ROWS, horizon), -0.01, np.float32)
    ends = rng.random(ROWS) < 0.3
    reward[ends, -1] = np.where(rng.random(int(ends.sum())) < 0.5, 1.0, -1.0)
    action = np.stack([rng.integers(0, b, (ROWS, horizon)) for b in BRANCHES], axis=-1)
    allowed = np.ones((ROWS, horizon, sum(BRANCHES)), bool)
    in_air = rng.random((ROWS, horizon)) < 1 / 3
    allowed[..., -1] = ~in_air
    action[..., -1] = np.where(in_air, 0, action[..., -1])
    obs = rng.normal(size=(ROWS, horizon + 1, OBS_SIZE)).astype(np.float32)
    return {"obs": obs, "reward": reward, "action": action, "ends": ends, "allowed": allowed}


def ours(seed: int, out: Path) -> None:
    import torch

    from learners.algorithms.ppo import PPO
    from learners.networks.policies import ActorCritic
    from learners.trainer_config.parse import load_config

    settings = load_config(CONFIG).for_behavior(BEHAVIOR)
    horizon = settings.time_horizon
    spec = branch_spec()
    torch.manual_seed(seed)
    network = ActorCritic(spec, settings.network_settings)
    initial = {k: v.detach().clone().numpy() for k, v in network.state_dict().items()}
    data = buffer(seed, horizon)
    n = ROWS * horizon
    steps, log_prob = packed_steps(spec, data, network)
    ppo = PPO(network, settings)
    ppo.add(steps, torch.zeros(n, dtype=torch.int64))
    report = update_in_order(ppo)
    after = {k: v.detach().numpy() for k, v in network.state_dict().items()}
    save_case(
        out, log_prob.numpy().reshape(ROWS, horizon, -1), data, initial, after, report, REPORTED
    )


def _split(weights: np.ndarray) -> list[np.ndarray]:
    """Our one logits layer's rows (or biases) per branch, as ML-Agents' layers."""
    return np.split(weights, np.cumsum(BRANCHES)[:-1])


def mlagents(case: Path, anchor: Path) -> float:
    anchor_workarounds(anchor)
    import torch
    import yaml
    from mlagents.plugins.trainer_type import register_trainer_plugins
    from mlagents.trainers.policy.torch_policy import TorchPolicy
    from mlagents.trainers.ppo.optimizer_torch import TorchPPOOptimizer
    from mlagents.trainers.settings import RunOptions
    from mlagents.trainers.torch_entities.networks import SimpleActor

    d = np.load(case)
    register_trainer_plugins()
    settings = RunOptions.from_dict(yaml.safe_load(CONFIG.read_text())).behaviors[BEHAVIOR]
    actor = {"conditional_sigma": False, "tanh_squash": False}
    policy = TorchPolicy(0, branch_spec(), settings.network_settings, SimpleActor, actor)
    optimizer = TorchPPOOptimizer(policy, settings)
    modules = {"actor": policy.actor, "critic": optimizer.critic}
    names = dict(ML_NAMES)
    for name, (module, theirs) in names.items():
        state = modules[module].state_dict()
        for part in ("weight", "bias"):
            state[f"{theirs}.{part}"] = torch.from_numpy(d[f"initial/{name}.{part}"])
        modules[module].load_state_dict(state)
    state = policy.actor.state_dict()
    for part in ("weight", "bias"):
        for index, rows in enumerate(_split(d[f"initial/logits.{part}"])):
            state[f"{ML_BRANCH.format(index)}.{part}"] = torch.from_numpy(rows)
    policy.actor.load_state_dict(state)

    figures = mlagents_update(policy, optimizer, settings, dict(d), d["log_prob"])

    rows = []
    after_actor = policy.actor.state_dict()
    for name, (module, theirs) in names.items():
        for part in ("weight", "bias"):
            mine, start = d[f"after/{name}.{part}"], d[f"initial/{name}.{part}"]
            theirs_now = modules[module].state_dict()[f"{theirs}.{part}"].numpy()
            rows.append((name, part, np.abs(theirs_now - mine).max(), np.abs(mine - start).max()))
    for part in ("weight", "bias"):
        mine, start = d[f"after/logits.{part}"], d[f"initial/logits.{part}"]
        theirs_now = np.concatenate(
            [after_actor[f"{ML_BRANCH.format(i)}.{part}"].numpy() for i in range(len(BRANCHES))]
        )
        rows.append(("logits", part, np.abs(theirs_now - mine).max(), np.abs(mine - start).max()))
    most = max(moved for *_, moved in rows)
    worst = 0.0
    for name, part, diff, moved in rows:
        print(f"  {name}.{part:<6} max |ML - ours| {diff:.1e}, moved by the update {moved:.1e}")
        worst = max(worst, diff / (moved if moved >= 1e-3 * most else most))
    return max(worst, worst_report_difference(figures, d, REPORTED))


if __name__ == "__main__":
    run_sides(__spec__.name, ours, mlagents, __doc__)
