"""POCA end to end on unitysim DungeonEscape (three knights a group, the sacrifice, the
group reward), in local 2-core mode: the group reward reaches the learner with no warning,
ML-Agents' POCA tags are written, resume brings the group critic back, and the policy
exports to ONNX and runs in onnxruntime."""

from __future__ import annotations

import json
import logging

import numpy as np
import onnxruntime as ort
import pytest
import torch

from driver.options import TrainOptions
from driver.training.train import train
from learners.host import checkpoint
from learners.host.export import export_checkpoint

pytestmark = pytest.mark.integration

CONFIG = """\
behaviors:
  DungeonEscape:
    trainer_type: poca
    hyperparameters: {batch_size: 256, buffer_size: 1024, learning_rate: 0.0003, beta: 0.01,
                      epsilon: 0.2, lambd: 0.95, num_epoch: 3, learning_rate_schedule: constant}
    network_settings: {normalize: false, hidden_units: 32, num_layers: 2}
    reward_signals: {extrinsic: {gamma: 0.99, strength: 1.0}}
    max_steps: 100000
    time_horizon: 64
    summary_freq: 2000
"""


@pytest.fixture(scope="module")
def poca_run(ray_session, tmp_path_factory):
    results = tmp_path_factory.mktemp("results")
    config = results / "poca.yaml"
    config.write_text(CONFIG)
    options = TrainOptions(
        env="unitysim:DungeonEscape",
        config=str(config),
        results_dir=str(results),
        run_id="knights",
        max_steps=6000,
        max_seconds=120,  # a safety stop: the budget is the steps
        workers=1,
        progress=False,
    )
    logger = logging.getLogger()
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = records.append  # type: ignore[method-assign]
    logger.addHandler(handler)
    try:
        result = train(options)
    finally:
        logger.removeHandler(handler)
    return options, result, [r.getMessage() for r in records]


def test_poca_trains_on_the_group_reward_and_writes_its_tags(poca_run):
    _, result, said = poca_run
    assert not [s for s in said if "group reward" in s], said
    summary = json.loads((result.run_dir / "summary.json").read_text())
    assert summary["ledger"]["balanced"], summary["ledger"]
    assert result.version >= 2  # updates of over 1024 steps
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (folder,) = [p for p in result.run_dir.iterdir() if p.name.startswith("DungeonEscape")]
    tags = EventAccumulator(str(folder)).Reload().Tags()["scalars"]
    for tag in (
        "Losses/Policy Loss",
        "Losses/Value Loss",
        "Losses/Baseline Loss",
        "Policy/Extrinsic Value Estimate",
        "Policy/Extrinsic Baseline Estimate",
        "Environment/Group Cumulative Reward",
        "Policy/Extrinsic Reward",
    ):
        assert tag in tags, tag


def test_resume_brings_the_group_critic_back(poca_run, ray_session):
    options, first, _ = poca_run
    state = checkpoint.load(first.checkpoint)
    (entry,) = state["behaviors"].values()
    critic = entry["algorithm"]["critic"]
    assert "value_head.weight" in critic and float(critic["most_agents"]) == 3.0
    resumed = train(
        TrainOptions(
            env=options.env,
            config=options.config,
            results_dir=options.results_dir,
            run_id=options.run_id,
            resume=True,
            max_steps=8000,
            max_seconds=120,
            workers=1,
            progress=False,
        )
    )
    assert resumed.version > first.version


def test_the_poca_policy_exports_and_runs_in_onnxruntime(poca_run, tmp_path):
    _, result, _ = poca_run
    (path,) = export_checkpoint(result.checkpoint, tmp_path)
    (network,) = checkpoint.networks(checkpoint.load(result.checkpoint)).values()
    rng = np.random.default_rng(0)
    obs = [
        rng.normal(size=(4, *o.shape)).astype(np.float32) for o in network.spec.observation_specs
    ]
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {f"obs_{i}": o for i, o in enumerate(obs)} | {
        "action_masks": np.ones((4, 7), np.float32)
    }
    (actions,) = session.run(["deterministic_discrete_actions"], feeds)
    with torch.no_grad():
        named = {n: torch.from_numpy(o) for n, o in zip(network.sensor_names, obs, strict=True)}
        _, expected, _ = network.act(named, None, True)
    np.testing.assert_array_equal(actions, expected.numpy())


STRIKERS = """\
behaviors:
  Goalie: &side
    trainer_type: poca
    hyperparameters: {batch_size: 128, buffer_size: 512, num_epoch: 1}
    network_settings: {hidden_units: 16, num_layers: 1}
    time_horizon: 32
    summary_freq: 1000
    self_play: {save_steps: 500, team_change: 1000, swap_steps: 500, window: 3}
  Striker: *side
"""


def test_a_goalie_alone_in_its_group_trains_when_its_team_learns(ray_session, tmp_path):
    """StrikersVsGoalie under ML-Agents' poca config shape: the Goalie has a group of its
    own, no groupmates; it takes its turn after the Strikers' and trains on it."""
    config = tmp_path / "strikers.yaml"
    config.write_text(STRIKERS)
    result = train(
        TrainOptions(
            env="unitysim:StrikersVsGoalie",
            config=str(config),
            results_dir=str(tmp_path),
            run_id="strikers",
            max_steps=5000,
            max_seconds=150,  # a safety stop: the budget is the steps
            workers=1,
            progress=False,
        )
    )
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (goalie,) = [p for p in result.run_dir.iterdir() if p.name.startswith("Goalie")]
    scalars = EventAccumulator(str(goalie)).Reload()
    assert scalars.Scalars("Losses/Baseline Loss"), "the Goalie never trained"
    assert scalars.Scalars("Self-play/ELO")
