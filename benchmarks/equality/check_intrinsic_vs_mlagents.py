"""Two PPO updates with an intrinsic reward signal, curiosity and then RND, ours and
mlagents-learn 1.1.0's own code, on the same buffers and weights.

ML-Agents' ``ppo/Pyramids.yaml`` (curiosity: strength 0.02, gamma 0.99, 256 units) and
``ppo/PyramidsRND.yaml`` (rnd: strength 0.01, 3 layers of 64, learning rate 1e-4) on a
small discrete behavior (one-hot observations, 3 moves), so that every part of an
update with the signal is compared exactly: the first update trains the signal's networks
(curiosity's rewards are still 0 then); the second reads its rewards (curiosity: the
forward model's error; RND: the predictor's distance from the fixed random network; times
the signal's strength), gives them their own value head and GAE, sums the signals'
advantages with the extrinsic one, and trains actor, critic, both value heads and the
signal's networks again. Minibatches are taken in order on both sides. The weights after
both updates must agree to float precision (policy, critic, value heads, every layer of
the signal's networks), and so must the second update's TensorBoard figures.

Runs as ``check_ppo_vs_mlagents.py`` does, ML-Agents' side in the anchor's venv:

    .venv/bin/python -m benchmarks.equality.check_intrinsic_vs_mlagents --seeds 0 1 2
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import mlagents_config
from benchmarks.equality.common import (
    BRANCH,
    OBS_SIZE,
    REPORTED,
    anchor_workarounds,
    load_ours,
    mlagents_ppo,
    mlagents_update,
    packed_steps,
    reported,
    run_sides,
    update_in_order,
    vector_spec,
    worst_difference,
    worst_report_difference,
)

BEHAVIOR, ROWS, UPDATES = "Pyramids", 17, 2  # the spec: common.py's (Basic's)
POLICY = {  # our parameter ("<module>:<name>") -> (ML-Agents' module, its parameter)
    "net:trunk.0": ("actor", "network_body._body_endoder.seq_layers.0"),
    "net:trunk.2": ("actor", "network_body._body_endoder.seq_layers.2"),
    "net:logits": ("actor", "action_model._discrete_distribution.branches.0"),
    "net:critic_trunk.0": ("critic", "network_body._body_endoder.seq_layers.0"),
    "net:critic_trunk.2": ("critic", "network_body._body_endoder.seq_layers.2"),
    "net:value": ("critic", "value_heads.value_heads.extrinsic"),
}


@dataclass(frozen=True)
class Case:
    """One signal: ML-Agents' config, its networks' parameters by name (ours, module
    "sig"; ML-Agents' modules by attribute of its reward provider), the figures compared."""

    config: str
    names: Mapping[str, tuple[str, str]]
    modules: Mapping[str, str]  # ML-Agents' module name -> reward provider attribute
    figures: tuple[str, ...]


def encoder(ours: str, module: str, body: str, layers: int) -> dict[str, tuple[str, str]]:
    """A ``NetworkBody``'s MLP: our ``Body``'s trunk against ML-Agents' ``body`` of ``module``."""
    return {
        f"sig:{ours}.network.trunk.{2 * i}": (module, f"{body}.seq_layers.{2 * i}")
        for i in range(layers)
    }


CASES = {
    "curiosity": Case(
        "ppo/Pyramids.yaml",
        {
            **encoder("body", "curiosity", "_state_encoder._body_endoder", 2),
            "sig:inverse.0": ("curiosity", "inverse_model_action_encoding.0.seq_layers.0"),
            "sig:discrete_head": ("curiosity", "discrete_action_prediction"),
            "sig:forward_model.0": (
                "curiosity",
                "forward_model_next_state_prediction.0.seq_layers.0",
            ),
            "sig:forward_model.2": ("curiosity", "forward_model_next_state_prediction.1"),
        },
        {"curiosity": "_network"},
        (*REPORTED, "Losses/Curiosity Forward Loss", "Losses/Curiosity Inverse Loss"),
    ),
    "rnd": Case(
        "ppo/PyramidsRND.yaml",
        {
            **encoder("target", "rnd_random", "_encoder._body_endoder", 3),
            **encoder("predictor", "rnd_trained", "_encoder._body_endoder", 3),
        },
        {"rnd_random": "_random_network", "rnd_trained": "_training_network"},
        (*REPORTED, "Losses/RND Loss"),
    ),
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
    """Both cases' updates, saved under each case's name."""
    saved: dict[str, Any] = {}
    for name, case in CASES.items():
        saved |= {f"{name}|{k}": v for k, v in ours_updates(seed, case).items()}
    np.savez(out, **saved)


def ours_updates(seed: int, case: Case) -> dict[str, Any]:
    import torch

    from learners.algorithms.ppo import PPO
    from learners.networks.policies import ActorCritic
    from learners.trainer_config.parse import load_config

    settings = load_config(mlagents_config(case.config)).for_behavior(BEHAVIOR)
    horizon = settings.time_horizon
    spec = vector_spec(OBS_SIZE, BRANCH)
    torch.manual_seed(seed)
    network = ActorCritic(spec, settings.network_settings)
    ppo = PPO(network, settings)
    signal = ppo.signals.items[0]
    modules = {"net": network, "heads": ppo.signals.heads, "sig": signal}

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
    for u in range(UPDATES):
        rows = {k: v[u] for k, v in data.items()}
        steps, log_prob = packed_steps(spec, rows, network, u, BEHAVIOR)  # acted now
        log_probs.append(log_prob.numpy().reshape(ROWS, horizon))
        ppo.add(steps, torch.full((ROWS * horizon,), u, dtype=torch.int64))
        assert ppo.ready()
        report = update_in_order(ppo)
        reward = report.get(f"Policy/{signal.stat} Reward")  # per finished episode
        said = "no episode ended" if reward is None else f"reward {reward:.2e} per episode"
        print(f"  ours, {signal.stat}, update {u}: {said}")
    return {
        "horizon": horizon,
        "log_prob": np.stack(log_probs),
        **data,
        **initial,
        **weights("after"),
        **reported(report, case.figures),
    }


def mlagents(case_file: Path, anchor: Path) -> float:
    """ML-Agents' PPO trainer, optimizer and reward provider on each case's buffers, as
    its trainer's ``_process_trajectory`` and ``_update_policy`` run them; returns the
    worst difference from our weights and figures, relative."""
    anchor_workarounds(anchor)
    saved = np.load(case_file)
    worst = 0.0
    for name, case in CASES.items():
        print(f"  {name}:")
        d = {k.split("|", 1)[1]: saved[k] for k in saved.files if k.startswith(f"{name}|")}
        policy, optimizer, settings = mlagents_ppo(mlagents_config(case.config), BEHAVIOR)
        provider = optimizer.reward_signals[name]
        modules = {"actor": policy.actor, "critic": optimizer.critic}
        modules |= {module: getattr(provider, attr) for module, attr in case.modules.items()}
        names = {**POLICY, "heads:0": ("critic", f"value_heads.value_heads.{name}"), **case.names}
        load_ours(modules, names, d)
        for u in range(UPDATES):
            rows = {k: d[k][u] for k in ("obs", "reward", "action", "ends")}
            figures = mlagents_update(policy, optimizer, settings, rows, d["log_prob"][u])
        weights = worst_difference(modules, names, d)
        worst = max(worst, weights, worst_report_difference(figures, d, case.figures))
    return worst


if __name__ == "__main__":
    run_sides(__spec__.name, ours, mlagents, __doc__)
