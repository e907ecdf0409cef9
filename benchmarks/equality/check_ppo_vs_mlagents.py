"""One PPO update, ours and mlagents-learn 1.1.0's own code, on the same buffer and weights.

Where learning curves can only be compared statistically, one update can be compared
exactly: the same initial weights, the same 270 steps (rows of ``time_horizon`` steps,
some ending their episode, the others cut and bootstrapped), the minibatches taken in
order instead of shuffled. Our side runs ``learners.algorithms.ppo.PPO.update`` (GAE, whole-buffer
advantage normalization, ``num_epoch`` passes, the loss, Adam); ML-Agents' side builds
its trajectories, value estimates, ``get_gae`` and ``TorchPPOOptimizer.update`` as its
PPO trainer does. The weights after the update must agree to float precision.

ML-Agents' side runs in the anchor recipe's venv (``--anchor``, as
``bench_vs_mlagents.py``) with the launcher's runtime workarounds: this module runs
itself there (``-m``, from the repository root) with ``--side mlagents``, importing
nothing of ours there but ``benchmarks.equality.common`` (``common.run_sides``, which
every check of this folder runs).

    .venv/bin/python -m benchmarks.equality.check_ppo_vs_mlagents --seeds 0 1 2
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.equality.common import (
    BEHAVIOR,
    BRANCH,
    CONFIG,
    OBS_SIZE,
    REPORTED,
    ROWS,
    anchor_workarounds,
    load_ours,
    mlagents_ppo,
    mlagents_update,
    packed_steps,
    run_sides,
    save_case,
    update_in_order,
    vector_spec,
    worst_difference,
    worst_report_difference,
)

# our parameter -> (ML-Agents' module: "actor" or "critic", its parameter)
ML_NAMES = {
    "trunk.0": ("actor", "network_body._body_endoder.seq_layers.0"),
    "logits": ("actor", "action_model._discrete_distribution.branches.0"),
    "critic_trunk.0": ("critic", "network_body._body_endoder.seq_layers.0"),
    "value": ("critic", "value_heads.value_heads.extrinsic"),
}


def buffer(seed: int, horizon: int) -> dict[str, np.ndarray]:
    """Rows of ``horizon`` steps: one-hot observations, -0.01 a step, 30 % of rows end
    their episode with +1 or +0.1 (terminated), the others are cut (bootstrapped)."""
    rng = np.random.default_rng(seed)
    reward = np.full((ROWS, horizon), -0.01, np.float32)
    ends = rng.random(ROWS) < 0.3
    reward[ends, -1] = np.where(rng.random(int(ends.sum())) < 0.5, 1.0, 0.1)
    return {
        "obs": np.eye(OBS_SIZE, dtype=np.float32)[rng.integers(0, OBS_SIZE, (ROWS, horizon + 1))],
        "reward": reward,
        "action": rng.integers(0, BRANCH, (ROWS, horizon)),
        "ends": ends,
    }


def ours(seed: int, out: Path) -> None:
    import torch

    from learners.algorithms.ppo import PPO
    from learners.networks.policies import ActorCritic
    from learners.trainer_config.parse import load_config

    settings = load_config(CONFIG).for_behavior(BEHAVIOR)
    horizon = settings.time_horizon
    spec = vector_spec(OBS_SIZE, BRANCH)
    torch.manual_seed(seed)
    network = ActorCritic(spec, settings.network_settings)
    initial = {k: v.detach().clone().numpy() for k, v in network.state_dict().items()}
    data = buffer(seed, horizon)
    n = ROWS * horizon
    steps, log_prob = packed_steps(spec, data, network)  # acted by the initial weights
    ppo = PPO(network, settings)
    ppo.add(steps, torch.zeros(n, dtype=torch.int64))
    assert ppo.ready()
    report = update_in_order(ppo)
    after = {k: v.detach().numpy() for k, v in network.state_dict().items()}
    save_case(
        out,
        log_prob.numpy().reshape(ROWS, horizon),
        data,
        initial,
        after,
        report,
        REPORTED,
        horizon=horizon,
    )


def mlagents(case: Path, anchor: Path) -> float:
    """ML-Agents' PPO trainer and optimizer on the case's buffer; returns the worst
    difference from our weights, relative to how far the update moved them."""
    anchor_workarounds(anchor)
    d = np.load(case)
    policy, optimizer, settings = mlagents_ppo(CONFIG, BEHAVIOR)
    modules = {"actor": policy.actor, "critic": optimizer.critic}
    load_ours(modules, ML_NAMES, d)
    figures = mlagents_update(policy, optimizer, settings, dict(d), d["log_prob"])
    return max(
        worst_difference(modules, ML_NAMES, d), worst_report_difference(figures, d, REPORTED)
    )


if __name__ == "__main__":
    run_sides(__spec__.name, ours, mlagents, __doc__)
