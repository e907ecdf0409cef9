"""``behavioral_cloning`` end to end, in local 2-core mode: Hallway's scripted expert
recorded with ``record-demo``, then PPO with memory (the shipped config) trained beside
cloning from that file (the pretraining loss in TensorBoard under ML-Agents' tag,
falling), and ML-Agents' ``imitation/Hallway.yaml`` (memory and GAIL) on it; a missing
file and a file of another behavior each one line naming it."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from demonstrations import write_demo
from driver.declaration import TrainingError
from driver.options import TrainOptions
from driver.training.train import train
from learners.reward_signals.cloning import REPORT
from rollout.serving.service import RolloutError
from tests.demonstrations.samples import CONTINUOUS, demonstration
from tests.driver.test_record_demo import record
from tests.helpers import assert_rewards_per_episode

pytestmark = pytest.mark.integration


def hallway_config(tmp_path: Path, demo: Path) -> Path:
    config = yaml.safe_load((Path(__file__).parents[2] / "config" / "Hallway.yaml").read_text())
    hallway = config["behaviors"]["Hallway"]
    hallway["hyperparameters"] |= {"buffer_size": 512, "batch_size": 128}
    hallway["summary_freq"] = 1000
    hallway["behavioral_cloning"] = {"demo_path": str(demo), "strength": 1.0, "steps": 0}
    path = tmp_path / "Hallway_bc.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def options(tmp_path: Path, config: Path, max_steps: int = 4_000) -> TrainOptions:
    return TrainOptions(
        env="unitysim:Hallway",
        config=str(config),
        results_dir=str(tmp_path / "results"),
        run_id="bc",
        workers=1,
        max_steps=max_steps,
        progress=False,
    )


def test_mlagents_imitation_hallway_config_trains_with_memory_and_gail(ray_session, tmp_path):
    """Unchanged but for its demo_path (a record-demo recording) and summary_freq."""
    demo = tmp_path / "ExpertHallway.demo"
    code, _, err = record(
        tmp_path, "--env", "unitysim:Hallway", "--heuristic", "--steps", "800", "--out", str(demo)
    )
    assert code == 0, err
    configs = Path(__file__).resolve().parents[1] / "mlagents_configs"
    config = yaml.safe_load((configs / "imitation" / "Hallway.yaml").read_text())
    hallway = config["behaviors"]["Hallway"]
    hallway["reward_signals"]["gail"]["demo_path"] = str(demo)
    hallway["summary_freq"] = 1000
    path = tmp_path / "Hallway.yaml"
    path.write_text(yaml.safe_dump(config))
    result = train(options(tmp_path, path, max_steps=2_100))
    scalars = EventAccumulator(str(result.run_dir / "Hallway")).Reload().Tags()["scalars"]
    for tag in ("Policy/Gail Value Estimate", "Losses/GAIL Loss", "Losses/Policy Loss"):
        assert tag in scalars, (tag, scalars)
    assert_rewards_per_episode(scalars, "Gail")


def test_ppo_clones_hallways_expert_beside_its_own_steps(ray_session, tmp_path):
    demo = tmp_path / "HallwayExpert.demo"
    code, _, err = record(
        tmp_path, "--env", "unitysim:Hallway", "--heuristic", "--steps", "1500", "--out", str(demo)
    )
    assert code == 0, err
    result = train(options(tmp_path, hallway_config(tmp_path, demo)))
    assert result.steps["Hallway?team=0"] >= 4_000
    events = EventAccumulator(str(result.run_dir / "Hallway")).Reload()
    losses = [e.value for e in events.Scalars(REPORT)]
    assert len(losses) >= 2, losses  # the summaries that followed updates
    assert 0 < losses[-1] < losses[0]  # the policy comes closer to the expert's choices


def test_a_missing_demonstration_is_one_line_before_anything_runs(tmp_path):
    config = hallway_config(tmp_path, tmp_path / "nowhere.demo")
    with pytest.raises(TrainingError) as error:
        train(options(tmp_path, config))
    message = str(error.value)
    assert message.startswith("behaviors.Hallway.behavioral_cloning.demo_path: ")
    assert "nowhere.demo" in message and "\n" not in message
    assert not (tmp_path / "results").exists()


def test_a_demonstration_of_another_behavior_is_one_line_naming_it(ray_session, tmp_path):
    other = tmp_path / "Walker.demo"
    write_demo(other, demonstration(CONTINUOUS, 30))
    # the driver (TrainingError) or the learner (RolloutError), whichever meets it first
    with pytest.raises((TrainingError, RolloutError)) as error:
        train(options(tmp_path, hallway_config(tmp_path, other), max_steps=1_000))
    message = str(error.value)
    assert "of Hallway: " in message and "Walker.demo: actions" in message
    assert "\n" not in message
