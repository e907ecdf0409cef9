"""ML-Agents' ``ppo/Pyramids.yaml`` (curiosity), ``ppo/PyramidsRND.yaml`` (RND),
``imitation/Pyramids.yaml`` and ``sac/Pyramids.yaml`` (GAIL, on a recording), their
summaries every 1,000 steps, past their first update on unitysim Pyramids in local
2-core mode: each signal's reward, value estimate and losses reach TensorBoard under
ML-Agents' tags."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from driver.options import TrainOptions
from driver.training.train import train
from tests.driver.test_record_demo import record
from tests.helpers import assert_rewards_per_episode

pytestmark = pytest.mark.integration

CONFIGS = Path(__file__).resolve().parents[1] / "mlagents_configs" / "ppo"


def train_pyramids(tmp_path: Path, data: dict, steps: int = 4_200) -> list[str]:
    """ML-Agents' ``data`` with summaries every 1,000 steps, ``steps`` on unitysim Pyramids
    (PPO's buffer_size 2048: two updates, with summaries between them); the scalar tags its
    TensorBoard folder holds."""
    data["behaviors"]["Pyramids"]["summary_freq"] = 1000
    path = tmp_path / "Pyramids.yaml"
    path.write_text(yaml.safe_dump(data))
    options = TrainOptions(
        env="unitysim:Pyramids",
        config=str(path),
        results_dir=str(tmp_path),
        run_id="signals",
        max_steps=steps,
        workers=1,
        progress=False,
    )
    result = train(options)
    assert not result.interrupted
    return EventAccumulator(str(result.run_dir / "Pyramids")).Reload().Tags()["scalars"]


def test_rnd_trains_beside_the_extrinsic_signal(ray_session, tmp_path):
    """(Curiosity: the imitation config below has it.)"""
    scalars = train_pyramids(tmp_path, yaml.safe_load((CONFIGS / "PyramidsRND.yaml").read_text()))
    for tag in ("Policy/Rnd Value Estimate", "Losses/RND Loss"):
        assert tag in scalars, (tag, scalars)
    assert_rewards_per_episode(scalars, "Rnd")
    assert "Policy/Extrinsic Value Estimate" in scalars


def test_mlagents_imitation_config_trains_with_gail_cloning_and_curiosity(ray_session, tmp_path):
    """ML-Agents' ``imitation/Pyramids.yaml``, its ``demo_path`` (twice) pointing at
    unitysim's expert recorded by ``record-demo``, its summaries every 1,000 steps."""
    demo = tmp_path / "ExpertPyramid.demo"
    code, _, err = record(
        tmp_path, "--env", "unitysim:Pyramids", "--heuristic", "--steps", "800", "--out", str(demo)
    )
    assert code == 0, err
    data = yaml.safe_load((CONFIGS.parent / "imitation" / "Pyramids.yaml").read_text())
    pyramids = data["behaviors"]["Pyramids"]
    pyramids["reward_signals"]["gail"]["demo_path"] = str(demo)
    pyramids["behavioral_cloning"]["demo_path"] = str(demo)
    scalars = train_pyramids(tmp_path, data)
    for tag in (
        "Policy/Gail Value Estimate",
        "Losses/GAIL Loss",
        "Policy/GAIL Expert Estimate",
        "Policy/Curiosity Value Estimate",
        "Losses/Curiosity Forward Loss",
        "Losses/Pretraining Loss",
    ):
        assert tag in scalars, (tag, scalars)
    assert_rewards_per_episode(scalars, "Gail", "Curiosity")


def test_mlagents_sac_pyramids_config_trains_with_gail(ray_session, tmp_path):
    """ML-Agents' ``sac/Pyramids.yaml`` (GAIL under SAC), its ``demo_path`` pointing at
    unitysim's expert recorded by ``record-demo``: the discriminator trains and the Qs
    have a GAIL stream."""
    demo = tmp_path / "ExpertPyramid.demo"
    code, _, err = record(
        tmp_path, "--env", "unitysim:Pyramids", "--heuristic", "--steps", "800", "--out", str(demo)
    )
    assert code == 0, err
    data = yaml.safe_load((CONFIGS.parent / "sac" / "Pyramids.yaml").read_text())
    data["behaviors"]["Pyramids"]["reward_signals"]["gail"]["demo_path"] = str(demo)
    scalars = train_pyramids(tmp_path, data, steps=2_200)  # gradient steps from 1,000 on
    for tag in ("Losses/GAIL Loss", "Policy/GAIL Expert Estimate", "Losses/Q1 Loss"):
        assert tag in scalars, (tag, scalars)
    assert_rewards_per_episode(scalars, "Gail")  # per episode, as ML-Agents' SAC reports it
