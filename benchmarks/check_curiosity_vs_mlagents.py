"""Two PPO updates with curiosity, ours and mlagents-learn 1.1.0's own code, on the same
buffers and weights.

ML-Agents' ``ppo/Pyramids.yaml`` (curiosity: strength 0.02, gamma 0.99, 256 units) on a
small discrete behavior (one-hot observations, 3 moves), so that every part of a
curiosity update is compared exactly: the first update trains the curiosity module while
its rewards are still 0; the second reads its rewards (the forward model's error, times
its strength), gives them their own value head and GAE, sums the signals' advantages
with the extrinsic one, and trains actor, critic, both value heads and the curiosity
module again. Minibatches are taken in order on both sides. The weights after both
updates must agree to float precision: policy, critic, value heads and every layer of
the curiosity module.

Runs as ``check_ppo_vs_mlagents.py`` does, ML-Agents' side in the anchor's venv:

    .venv/bin/python benchmarks/check_curiosity_vs_mlagents.py --seeds 0 1 2
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from check_ppo_vs_mlagents import (
    BRANCH,
    OBS_SIZE,
    REPORTED,
    anchor_workarounds,
    load_ours,
    main,
    mlagents_ppo,
    mlagents_update,
    packed_steps,
    reported,
    vector_spec,
    worst_difference,
    worst_report_difference,
)

CONFIG = Path(__file__).resolve().parent / "mlagents_configs" / "ppo_Pyramids.yaml"
BEHAVIOR, ROWS, UPDATES = "Pyramids", 17, 2  # the spec: check_ppo_vs_mlagents.py's
# the second update's TensorBoard figures, compared
FIGURES = (*REPORTED, "Losses/Curiosity Forward Loss", "Losses/Curiosity Inverse Loss")
# our parameter ("<module>:<name>") -> (ML-Agents' module, its parameter)
ML_NAMES = {
    "net:trunk.0": ("actor", "network_body._body_endoder.seq_layers.0"),
    "net:trunk.2": ("actor", "network_body._body_endoder.seq_layers.2"),
    "net:logits": ("actor", "action_model._discrete_distribution.branches.0"),
    "net:critic_trunk.0": ("critic", "network_body._body_endoder.seq_layers.0"),
    "net:critic_trunk.2": ("critic", "network_body._body_endoder.seq_layers.2"),
    "net:value": ("critic", "value_heads.value_heads.extrinsic"),
    "heads:0": ("critic", "value_heads.value_heads.curiosity"),
    "cur:body.network.trunk.0": ("curiosity", "_state_encoder._body_endoder.seq_layers.0"),
    "cur:body.network.trunk.2": ("curiosity", "_state_encoder._body_endoder.seq_layers.2"),
    "cur:inverse.0": ("curiosity", "inverse_model_action_encoding.0.seq_layers.0"),
    "cur:discrete_head": ("curiosity", "discrete_action_prediction"),
    "cur:forward_model.0": ("curiosity", "forward_model_next_state_prediction.0.seq_layers.0"),
    "cur:forward_model.2": ("curiosity", "forward_model_next_state_prediction.1"),
}


def buffers(seed: int, horizon: int) -> dict[str, np.ndarray]:
    """``UPDATES`` buffers of ``ROWS`` rows of ``horizon`` steps: one-hot observations that
    follow the action (a walk on a ring, so that curiosity has something to learn), -0.01
    a step, 30 % of rows end their episode with +1 (terminated), the others are cut."""
    rng = np.random.default_rng(seed)
    shape = (UPDATES, ROWS, horizon)
    action = rng.integers(0, BRANCH, shape)
    position = np.zeros((UPDATES, ROWS, horizon + 1), np.int64)
    position[..., 0] = rng.integers(0, OBS_SIZE, (UPDATES, ROWS))
    for t in range(horizon):
        position[..., t + 1] = (position[..., t] + action[..., t] - 1) % OBS_SIZE
    reward = np.full(shape, -0.01, np.float32)
    ends = rng.random((UPDATES, ROWS)) < 0.3
    reward[..., -1] += np.where(ends, 1.0, 0.0)
    return {
        "obs": np.eye(OBS_SIZE, dtype=np.float32)[position],
        "reward": reward,
        "action": action,
        "ends": ends,
    }


def ours(seed: int, out: Path) -> None:
    import torch

    from learners.config import load_config
    from learners.policies import ActorCritic
    from learners.ppo import PPO

    settings = load_config(CONFIG).for_behavior(BEHAVIOR)
    horizon = settings.time_horizon
    spec = vector_spec(OBS_SIZE, BRANCH)
    torch.manual_seed(seed)
    network = ActorCritic(spec, settings.network_settings)
    ppo = PPO(network, settings)
    curiosity = ppo.signals.items[0]
    modules = {"net": network, "heads": ppo.signals.heads, "cur": curiosity}

    def weights(prefix: str) -> dict[str, np.ndarray]:
        return {
            f"{prefix}/{m}:{k}": v.detach().clone().numpy()
            for m, module in modules.items()
            for k, v in module.state_dict().items()
            if k != "updated"
        }

    initial = weights("initial")
    data = buffers(seed, horizon)
    log_probs = []
    in_order = lambda size, device=None: torch.arange(size, device=device)  # noqa: E731
    for u in range(UPDATES):
        rows = {k: v[u] for k, v in data.items()}
        steps, log_prob = packed_steps(
            spec, rows, network, u, BEHAVIOR
        )  # acted by the weights of now
        log_probs.append(log_prob.numpy().reshape(ROWS, horizon))
        ppo.add(steps, torch.full((ROWS * horizon,), u, dtype=torch.int64))
        assert ppo.ready()
        shuffle, torch.randperm = torch.randperm, in_order  # in order, as ML's side below
        try:
            report = ppo.update(0.0)
        finally:
            torch.randperm = shuffle
        print(f"  ours, update {u}: curiosity reward {report['Policy/Curiosity Reward']:.2e}")
    after = weights("after")
    figures = reported(report, FIGURES)
    np.savez(
        out, horizon=horizon, log_prob=np.stack(log_probs), **data, **initial, **after, **figures
    )


def mlagents(case: Path, anchor: Path) -> float:
    """ML-Agents' PPO trainer, optimizer and curiosity provider on the case's buffers, as
    its trainer's ``_process_trajectory`` and ``_update_policy`` run them; returns the
    worst difference from our weights, relative to how far the updates moved them."""
    anchor_workarounds(anchor)
    d = np.load(case)
    policy, optimizer, settings = mlagents_ppo(CONFIG, BEHAVIOR)
    curiosity = optimizer.reward_signals["curiosity"]._network
    modules = {"actor": policy.actor, "critic": optimizer.critic, "curiosity": curiosity}
    load_ours(modules, ML_NAMES, d)
    for u in range(UPDATES):
        rows = {k: d[k][u] for k in ("obs", "reward", "action", "ends")}
        figures = mlagents_update(policy, optimizer, settings, rows, d["log_prob"][u])
    return max(worst_difference(modules, ML_NAMES, d), worst_report_difference(figures, d, FIGURES))


if __name__ == "__main__":
    main(__file__, ours, mlagents, __doc__)
