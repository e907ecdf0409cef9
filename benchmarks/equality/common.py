"""What the exact checks against mlagents-learn 1.1.0's own code share: running both sides
(ours in this venv, ML-Agents' in the anchor recipe's, ``run_sides``), the Basic case most
of them start from (one vector sensor, one discrete branch), our packed steps of a case's
rows, ML-Agents' PPO built and updated as its trainer does, and the comparison of the
weights and TensorBoard figures after an update.

The anchor's Python imports this module (``python -m`` from the repository root), so at
the top it imports the standard library and numpy only; ours and ML-Agents' modules are
imported inside the functions that need them.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import ROOT, mlagents_config

CONFIG = mlagents_config("ppo/Basic.yaml")
BEHAVIOR, OBS_SIZE, BRANCH = "Basic", 20, 3  # Basic's spec: a one-hot position, 3 moves
ROWS = 90
TOLERANCE = 1e-3  # of how far the update moved each parameter; of each reported loss
REPORTED = ("Losses/Policy Loss", "Losses/Value Loss")  # TensorBoard figures compared


def vector_spec(obs_size: int, branch: int) -> Any:
    """A behavior of one vector sensor ``"v"`` and one discrete branch (both venvs)."""
    from mlagents_envs.base_env import (
        ActionSpec,
        BehaviorSpec,
        DimensionProperty,
        ObservationSpec,
        ObservationType,
    )

    sensor = ObservationSpec((obs_size,), (DimensionProperty.NONE,), ObservationType.DEFAULT, "v")
    return BehaviorSpec([sensor], ActionSpec(0, (branch,)))


def packed_steps(
    spec: Any, data: dict[str, np.ndarray], network: Any, version: int = 0, behavior: str = BEHAVIOR
) -> tuple[Any, Any]:
    """Our packed steps of ``data``'s rows (``obs`` one longer than each row: the last is
    what follows it), each row ending at its last step, terminated where ``ends``, acted
    by ``network`` (its log-probabilities, also returned) at ``version``; an action per
    branch where ``action`` has a branch axis, and ``allowed`` masks if given."""
    import torch

    from batches import keys
    from batches.specs import log_prob_size, spec_to_dict, step_spec

    rows, horizon = data["reward"].shape
    size, n = data["obs"].shape[-1], rows * horizon
    width = sum(spec.action_spec.discrete_branches)
    last = np.zeros((rows, horizon), bool)
    last[:, -1] = True
    terminated = last & data["ends"][:, None]
    steps = step_spec(spec).expand(n).zero()
    steps[keys.OBS, "v"] = torch.from_numpy(data["obs"][:, :-1].reshape(n, size))
    steps[keys.NEXT, keys.OBS, "v"] = torch.from_numpy(data["obs"][:, 1:].reshape(n, size))
    steps[keys.NEXT, keys.REWARD] = torch.from_numpy(data["reward"].reshape(n, 1))
    steps[keys.NEXT, keys.DONE] = torch.from_numpy(last.reshape(n, 1))
    steps[keys.NEXT, keys.TERMINATED] = torch.from_numpy(terminated.reshape(n, 1))
    steps[keys.NEXT, keys.TRUNCATED] = torch.from_numpy((last & ~terminated).reshape(n, 1))
    steps[keys.ACTION, keys.DISCRETE] = torch.from_numpy(data["action"].reshape(n, -1))
    allowed = data.get("allowed")
    steps[keys.ACTION_MASK] = (
        torch.ones(n, width, dtype=torch.bool)
        if allowed is None
        else torch.from_numpy(allowed.reshape(n, width))
    )
    steps[keys.POLICY_VERSION] = torch.full((n,), version, dtype=torch.int64)
    with torch.no_grad():
        log_prob, _, _ = network.evaluate(
            {"v": steps[keys.OBS, "v"]},
            None,
            steps[keys.ACTION, keys.DISCRETE],
            None if allowed is None else steps[keys.ACTION_MASK],
        )
    assert log_prob.shape[-1] == log_prob_size(spec)
    steps[keys.LOG_PROB] = log_prob
    steps.set_non_tensor(keys.BEHAVIOR, f"{behavior}?team=0")
    steps.set_non_tensor(keys.SPEC, spec_to_dict(spec))
    return steps, log_prob


def update_in_order(algorithm: Any) -> dict[str, float]:
    """``algorithm.update(0.0)`` with its minibatches taken in order, as ML-Agents' side
    takes them here (its trainer shuffles); the update's report."""
    import torch

    in_order = lambda size, device=None, generator=None: torch.arange(size, device=device)  # noqa: E731
    shuffle, torch.randperm = torch.randperm, in_order
    try:
        return algorithm.update(0.0)
    finally:
        torch.randperm = shuffle


def save_case(
    out: Path,
    log_prob: np.ndarray,
    rows: Mapping[str, np.ndarray],
    initial: Mapping[str, np.ndarray],
    after: Mapping[str, np.ndarray],
    report: dict[str, float],
    tags: tuple[str, ...],
    **extra: Any,
) -> None:
    """Our side of a case for ML-Agents' side to read: the rows, the log-probabilities that
    acted them, our weights before and after the update, and its figures ``tags``."""
    np.savez(
        out,
        **extra,
        log_prob=log_prob,
        **rows,
        **{f"initial/{k}": v for k, v in initial.items()},
        **{f"after/{k}": v for k, v in after.items()},
        **reported(report, tags),
    )


def reported(report: dict[str, float], tags: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Our update's TensorBoard figures ``tags``, to save beside the weights."""
    return {f"report/{tag}": np.array(report[tag]) for tag in tags}


def worst_report_difference(
    theirs: dict[str, float], d: np.lib.npyio.NpzFile, tags: tuple[str, ...]
) -> float:
    """The worst relative difference of ML-Agents' TensorBoard figures ``tags`` (its
    update's means over minibatches) from ours."""
    worst = 0.0
    for tag in tags:
        mine = float(d[f"report/{tag}"])
        difference = abs(theirs[tag] - mine) / max(abs(theirs[tag]), 1e-12)
        print(f"  {tag:<32} ML {theirs[tag]:.6g}, ours {mine:.6g}")
        worst = max(worst, difference)
    return worst


def anchor_workarounds(anchor: Path) -> None:
    """The anchor launcher's runtime workarounds, before ML-Agents is imported."""
    preamble = (anchor / "mlagents_learn_launcher.py").read_text()
    preamble = preamble.split("from mlagents.trainers.learn import main")[0]
    exec(compile(preamble, "mlagents_learn_launcher.py", "exec"), {})


def load_ours(modules: dict, names: dict, d: np.lib.npyio.NpzFile) -> None:
    """Our initial weights into ML-Agents' modules, by ``names`` (ours -> (module, theirs))."""
    import torch

    for name, (module, theirs) in names.items():
        state = modules[module].state_dict()
        for part in parts(d, name):
            state[f"{theirs}.{part}"] = torch.from_numpy(d[f"initial/{name}.{part}"])
        modules[module].load_state_dict(state)


def parts(d: Mapping[str, np.ndarray], name: str) -> list[str]:
    """The parameters of our module ``name`` in the case (a layer's ``weight`` and
    ``bias``, an LSTM's ``weight_ih_l0`` ...)."""
    prefix = f"initial/{name}."
    return [key.removeprefix(prefix) for key in d if key.startswith(prefix)]


def worst_difference(
    modules: dict, names: dict, d: np.lib.npyio.NpzFile, no_gradient: frozenset[str] = frozenset()
) -> float:
    """The worst difference of ML-Agents' weights after its update from ours, relative to
    how far the update moved each parameter; a parameter it did not move (by less than a
    thousandth of the most any moved: one with no gradient, as an attention key's bias,
    moves by Adam's step on rounding noise) is compared with that most. ``no_gradient``:
    parameters whose gradient is zero by construction (an attention key's bias, where the
    softmax over keys cancels it): Adam moves them on rounding noise alone, up to its full
    step, so they are shown and not compared."""
    rows = []
    for name, (module, theirs) in names.items():
        for part in parts(d, name):
            if f"{name}.{part}" in no_gradient:
                moved = float(np.abs(d[f"after/{name}.{part}"] - d[f"initial/{name}.{part}"]).max())
                print(f"  {name}.{part:<12} no gradient by construction: moved by {moved:.1e}")
                continue
            mine = d[f"after/{name}.{part}"]
            diff = float(
                np.abs(modules[module].state_dict()[f"{theirs}.{part}"].numpy() - mine).max()
            )
            moved = float(np.abs(mine - d[f"initial/{name}.{part}"]).max())
            print(f"  {name}.{part:<12} max |ML - ours| {diff:.1e}, moved by {moved:.1e}")
            rows.append((diff, moved))
    most = max(moved for _, moved in rows)
    return max(diff / (moved if moved >= 1e-3 * most else most) for diff, moved in rows)


def mlagents_ppo(
    config: Path | dict[str, Any], behavior: str, spec: Any = None
) -> tuple[Any, Any, Any]:
    """ML-Agents' PPO policy, optimizer and settings for ``behavior`` of ``config`` (a
    file, or its data), on ``spec`` (``vector_spec(OBS_SIZE, BRANCH)`` unless given),
    built as its PPO trainer builds them."""
    import yaml
    from mlagents.plugins.trainer_type import register_trainer_plugins
    from mlagents.trainers.policy.torch_policy import TorchPolicy
    from mlagents.trainers.ppo.optimizer_torch import TorchPPOOptimizer
    from mlagents.trainers.settings import RunOptions
    from mlagents.trainers.torch_entities.networks import SimpleActor

    register_trainer_plugins()
    text = config.read_text() if isinstance(config, Path) else yaml.safe_dump(config)
    settings = RunOptions.from_dict(yaml.safe_load(text)).behaviors[behavior]
    actor = {"conditional_sigma": False, "tanh_squash": False}  # as its PPO trainer
    spec = spec or vector_spec(OBS_SIZE, BRANCH)
    policy = TorchPolicy(0, spec, settings.network_settings, SimpleActor, actor)
    return policy, TorchPPOOptimizer(policy, settings), settings


def mlagents_update(
    policy: Any, optimizer: Any, settings: Any, rows: dict[str, np.ndarray], log_prob: Any
) -> dict[str, float]:
    """One update of ML-Agents' PPO on ``rows`` (as ``buffer``'s; an action and a
    log-probability per branch where they have a branch axis, ``allowed`` masks if given),
    each row one trajectory
    as its trainer's ``_process_trajectory`` takes it (value estimates, every reward
    signal's rewards times its strength, GAE with its gamma, the signals' advantages
    averaged), then ``train_in_order``; its figures."""
    from mlagents.trainers.buffer import AgentBuffer, BufferKey, RewardSignalUtil
    from mlagents.trainers.trainer.trainer_utils import get_gae
    from mlagents.trainers.trajectory import ObsUtil

    update, (count, horizon) = AgentBuffer(), rows["reward"].shape
    sensors = sensor_rows(rows)
    for row in range(count):
        trajectory, done = AgentBuffer(), bool(rows["ends"][row])
        for t in range(horizon):
            for i, obs in enumerate(sensors):
                trajectory[ObsUtil.get_name_at(i)].append(obs[row, t])
                trajectory[ObsUtil.get_name_at_next(i)].append(obs[row, t + 1])
            trajectory[BufferKey.ENVIRONMENT_REWARDS].append(rows["reward"][row, t])
            trajectory[BufferKey.DISCRETE_ACTION].append(np.atleast_1d(rows["action"][row, t]))
            trajectory[BufferKey.CONTINUOUS_ACTION].append(np.zeros(0, np.float32))
            trajectory[BufferKey.DISCRETE_LOG_PROBS].append(np.atleast_1d(log_prob[row, t]))
            trajectory[BufferKey.CONTINUOUS_LOG_PROBS].append(np.zeros(0, np.float32))
            allowed = rows["allowed"][row, t] if "allowed" in rows else np.ones(BRANCH)
            trajectory[BufferKey.ACTION_MASK].append(allowed.astype(np.float32))
            trajectory[BufferKey.MASKS].append(1.0)
            trajectory[BufferKey.DONE].append(done and t == horizon - 1)
        values, value_next, _ = optimizer.get_trajectory_value_estimates(
            trajectory, [obs[row, horizon] for obs in sensors], done
        )
        advantages = []
        for name, signal in optimizer.reward_signals.items():
            trajectory[RewardSignalUtil.value_estimates_key(name)].extend(values[name])
            advantage = get_gae(
                rewards=signal.evaluate(trajectory) * signal.strength,
                value_estimates=values[name],
                value_next=value_next[name],
                gamma=signal.gamma,
                lambd=settings.hyperparameters.lambd,
            )
            trajectory[RewardSignalUtil.returns_key(name)].set(advantage + values[name])
            trajectory[RewardSignalUtil.advantage_key(name)].set(advantage)
            advantages.append(advantage)
        trajectory[BufferKey.ADVANTAGES].set(list(np.mean(advantages, axis=0)))
        trajectory.resequence_and_append(update, training_length=policy.sequence_length)
    return train_in_order(update, optimizer, settings.hyperparameters)


def sensor_rows(rows: Mapping[str, np.ndarray]) -> list[np.ndarray]:
    """A case's observations, one array per sensor in spec order: ``obs`` for one sensor,
    ``obs/0``, ``obs/1``, ... for several."""
    if "obs" in rows:
        return [rows["obs"]]
    return [rows[f"obs/{i}"] for i in range(sum(k.startswith("obs/") for k in rows))]


def train_in_order(update: Any, optimizer: Any, h: Any, length: int = 1) -> dict[str, float]:
    """ML-Agents' ``_update_policy`` on its update buffer: the whole-buffer advantage
    normalization (padding's zeros included, with memory), then ``num_epoch`` passes of
    its optimizer's ``update`` over the minibatches of ``batch_size // length`` sequences
    of ``length`` (the sequence length; 1 without memory), in order (its trainer shuffles
    here; ours is told not to either), each also training the reward signals' networks;
    the means of what they report, as its trainer averages them for TensorBoard."""
    from mlagents.trainers.buffer import BufferKey

    advantages = np.array(update[BufferKey.ADVANTAGES].get_batch(), dtype=np.float32)
    normalized = (advantages - advantages.mean()) / (advantages.std() + 1e-10)
    update[BufferKey.ADVANTAGES].set(normalized)
    n, figures = update.num_experiences, {}
    size = max(h.batch_size - h.batch_size % length, length)  # whole sequences
    for _ in range(h.num_epoch):
        for start in range(0, (n // size) * size, size):
            minibatch = update.make_mini_batch(start, start + size)
            stats = optimizer.update(minibatch, max(h.batch_size // length, 1))
            stats.update(optimizer.update_reward_signals(minibatch))  # curiosity's ...
            for tag, value in stats.items():
                figures.setdefault(tag, []).append(float(value))
    return {tag: float(np.mean(values)) for tag, values in figures.items()}


def run_sides(
    module: str,
    ours: Callable[[int, Path], None],
    mlagents: Callable[[Path, Path], float],
    description: str,
) -> None:
    """A check's ``main``: both sides on each seed's case, ours in this venv and ML-Agents'
    in the anchor's, each running ``module`` (the check, ``python -m`` from the repository
    root: the anchor's Python imports this package and nothing else of ours); exits 1
    unless they agree within ``TOLERANCE``."""
    parser = argparse.ArgumentParser(description=description.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--anchor", type=Path, default=os.environ.get("MLAGENTS_ANCHOR", "/tmp/mlbench")
    )
    parser.add_argument("--side", choices=["ours", "mlagents"], help=argparse.SUPPRESS)
    parser.add_argument("--case", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.side == "ours":
        ours(args.seeds[0], args.case)
        return
    if args.side == "mlagents":
        worst = mlagents(args.case, args.anchor)
        print(f"worst relative difference {worst:.1e}")
        sys.exit(0 if worst <= TOLERANCE else 1)
    if not (args.anchor / "mlagents_learn_launcher.py").is_file():
        sys.exit(f"error: no mlagents-learn anchor in {args.anchor}: run the anchor recipe first")
    failed = []
    with tempfile.TemporaryDirectory() as work:
        for seed in args.seeds:
            case = Path(work) / f"case-{seed}.npz"
            me = [sys.executable, "-m", module, "--case", str(case), "--anchor", str(args.anchor)]
            subprocess.run([*me, "--side", "ours", "--seeds", str(seed)], check=True, cwd=ROOT)
            print(f"seed {seed}: ML-Agents' code against ours")
            theirs = [str(args.anchor / "venv/bin/python"), *me[1:], "--side", "mlagents"]
            env = {**os.environ, "PYTHONPATH": str(args.anchor / "shim")}
            if subprocess.run(theirs, env=env, cwd=ROOT).returncode != 0:
                failed.append(seed)
    print("agree" if not failed else f"DIFFER for seeds {failed}")
    sys.exit(1 if failed else 0)
