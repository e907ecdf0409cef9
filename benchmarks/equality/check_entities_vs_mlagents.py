"""One PPO update through entity attention, ours and mlagents-learn 1.1.0's own code, on the
same buffer and weights.

As ``check_ppo_vs_mlagents.py`` does for a vector sensor, on Sorter's layout made small: a
variable-length sensor first (a ``BufferSensor`` of up to 6 entities of 5 numbers, a random
count present each step, the rest zero rows), then a vector of 4, one branch of 3. Both sides
start from our initial weights, the attention's (the self encoding, the entity embedding, the
residual self-attention) of the actor and of the critic among them; ML-Agents' side runs its
``ObservationEncoder`` path (``EntityEmbedding``, ``ResidualSelfAttention``) in its PPO
trainer's steps and ``TorchPPOOptimizer.update``. The weights after the update must agree to
float precision; the attention keys' biases, whose gradient the softmax over keys cancels, move
on rounding noise alone on both sides and are shown, not compared.

    .venv/bin/python -m benchmarks.equality.check_entities_vs_mlagents --seeds 0 1 2
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.equality.common import (
    REPORTED,
    anchor_workarounds,
    load_ours,
    mlagents_ppo,
    mlagents_update,
    run_sides,
    save_case,
    update_in_order,
    worst_difference,
    worst_report_difference,
)

BEHAVIOR, ENTITIES, SIZE, VECTOR, BRANCH = "Sorter", 6, 5, 4, 3
ROWS, HORIZON = 24, 16
CONFIG = {
    "behaviors": {
        BEHAVIOR: {
            "trainer_type": "ppo",
            "hyperparameters": {
                "batch_size": 64,
                "buffer_size": ROWS * HORIZON,
                "learning_rate": 3.0e-3,
                "beta": 0.01,
                "epsilon": 0.2,
                "lambd": 0.95,
                "num_epoch": 2,
                "learning_rate_schedule": "constant",
            },
            "network_settings": {"normalize": False, "hidden_units": 32, "num_layers": 2},
            "reward_signals": {"extrinsic": {"gamma": 0.99, "strength": 1.0}},
            "time_horizon": HORIZON,
        }
    }
}
ENCODER = "network_body.observation_encoder"
ATTENTION = {
    "entities.own.0": f"{ENCODER}.x_self_encoder.seq_layers.0",
    "entities.embeddings.0.0": f"{ENCODER}.processors.0.self_ent_encoder.seq_layers.0",
    **{f"entities.attention.{ours}": f"{ENCODER}.rsa.fc_{ours}" for ours in ("q", "k", "v", "out")},
}
BODY = "network_body._body_endoder.seq_layers"
TRUNKS = (("", "actor"), ("critic_", "critic"))
# our parameter -> (ML-Agents' module: "actor" or "critic", its parameter)
ML_NAMES = {
    **{ours: ("actor", theirs) for ours, theirs in ATTENTION.items()},
    **{f"critic_{ours}": ("critic", theirs) for ours, theirs in ATTENTION.items()},
    **{f"trunk.{i}": ("actor", f"network_body._body_endoder.seq_layers.{i}") for i in (0, 2)},
    **{
        f"critic_trunk.{i}": ("critic", f"network_body._body_endoder.seq_layers.{i}")
        for i in (0, 2)
    },
    "logits": ("actor", "action_model._discrete_distribution.branches.0"),
    "value": ("critic", "value_heads.value_heads.extrinsic"),
}


def spec() -> Any:
    """The buffer first, as Unity sorts ``BufferSensor`` before a ``VectorSensor`` (both venvs)."""
    from mlagents_envs.base_env import (
        ActionSpec,
        BehaviorSpec,
        DimensionProperty,
        ObservationSpec,
        ObservationType,
    )

    variable = (DimensionProperty.VARIABLE_SIZE, DimensionProperty.NONE)
    return BehaviorSpec(
        [
            ObservationSpec((ENTITIES, SIZE), variable, ObservationType.DEFAULT, "b"),
            ObservationSpec((VECTOR,), (DimensionProperty.NONE,), ObservationType.DEFAULT, "v"),
        ],
        ActionSpec(0, (BRANCH,)),
    )


def buffer(seed: int) -> dict[str, np.ndarray]:
    """Rows of ``HORIZON`` steps (each observation list one longer: what follows the row):
    0 to 6 entities present per step; the reward is the first entity's first number;
    a third of the rows end their episode."""
    rng = np.random.default_rng(seed)
    entities = rng.uniform(0.2, 1.0, (ROWS, HORIZON + 1, ENTITIES, SIZE)).astype(np.float32)
    present = rng.integers(0, ENTITIES + 1, (ROWS, HORIZON + 1))
    entities[np.arange(ENTITIES) >= present[..., None]] = 0.0
    vector = rng.normal(size=(ROWS, HORIZON + 1, VECTOR)).astype(np.float32)
    return {
        "obs/0": entities,
        "obs/1": vector,
        "reward": entities[:, 1:, 0, 0] - 0.3,
        "action": rng.integers(0, BRANCH, (ROWS, HORIZON)),
        "ends": rng.random(ROWS) < 0.3,
    }


def packed(data: dict[str, np.ndarray], network: Any) -> tuple[Any, Any]:
    """Our packed steps of the rows, acted by ``network`` (its log-probabilities too)."""
    import torch

    from batches import keys
    from batches.specs import spec_to_dict, step_spec

    n = ROWS * HORIZON
    last = np.zeros((ROWS, HORIZON), bool)
    last[:, -1] = True
    terminated = last & data["ends"][:, None]
    steps = step_spec(spec()).expand(n).zero()
    for i, name in enumerate(("b", "v")):
        obs = data[f"obs/{i}"]
        steps[keys.OBS, name] = torch.from_numpy(obs[:, :-1].reshape(n, *obs.shape[2:]).copy())
        nxt = obs[:, 1:].reshape(n, *obs.shape[2:]).copy()
        steps[keys.NEXT, keys.OBS, name] = torch.from_numpy(nxt)
    steps[keys.NEXT, keys.REWARD] = torch.from_numpy(data["reward"].reshape(n, 1))
    steps[keys.NEXT, keys.DONE] = torch.from_numpy(last.reshape(n, 1))
    steps[keys.NEXT, keys.TERMINATED] = torch.from_numpy(terminated.reshape(n, 1))
    steps[keys.NEXT, keys.TRUNCATED] = torch.from_numpy((last & ~terminated).reshape(n, 1))
    steps[keys.ACTION, keys.DISCRETE] = torch.from_numpy(data["action"].reshape(n, 1))
    steps[keys.ACTION_MASK] = torch.ones(n, BRANCH, dtype=torch.bool)
    steps[keys.POLICY_VERSION] = torch.zeros(n, dtype=torch.int64)
    with torch.no_grad():
        obs = {name: steps[keys.OBS, name] for name in ("b", "v")}
        log_prob, _, _ = network.evaluate(obs, None, steps[keys.ACTION, keys.DISCRETE])
    steps[keys.LOG_PROB] = log_prob
    steps.set_non_tensor(keys.BEHAVIOR, f"{BEHAVIOR}?team=0")
    steps.set_non_tensor(keys.SPEC, spec_to_dict(spec()))
    return steps, log_prob


def ours(seed: int, out: Path) -> None:
    import torch

    from learners.algorithms.ppo import PPO
    from learners.networks.policies import ActorCritic
    from learners.trainer_config.parse import parse_config

    settings = parse_config(CONFIG).for_behavior(BEHAVIOR)
    torch.manual_seed(seed)
    network = ActorCritic(spec(), settings.network_settings)
    initial = {k: v.detach().clone().numpy() for k, v in network.state_dict().items()}
    data = buffer(seed)
    steps, log_prob = packed(data, network)
    ppo = PPO(network, settings)
    ppo.add(steps, torch.zeros(ROWS * HORIZON, dtype=torch.int64))
    report = update_in_order(ppo)
    after = {k: v.detach().numpy() for k, v in network.state_dict().items()}
    save_case(out, log_prob.numpy().reshape(ROWS, HORIZON), data, initial, after, report, REPORTED)


def mlagents(case: Path, anchor: Path) -> float:
    """ML-Agents' PPO trainer and optimizer on the case's buffer; returns the worst
    difference from our weights, relative to how far the update moved them."""
    anchor_workarounds(anchor)
    d = np.load(case)
    policy, optimizer, settings = mlagents_ppo(CONFIG, BEHAVIOR, spec())
    modules = {"actor": policy.actor, "critic": optimizer.critic}
    load_ours(modules, ML_NAMES, d)
    figures = mlagents_update(policy, optimizer, settings, dict(d), d["log_prob"])
    keys = frozenset(f"{owner}entities.attention.k.bias" for owner in ("", "critic_"))
    return max(
        worst_difference(modules, ML_NAMES, d, keys), worst_report_difference(figures, d, REPORTED)
    )


if __name__ == "__main__":
    run_sides(__spec__.name, ours, mlagents, __doc__)
