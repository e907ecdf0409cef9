"""ML-Agents' ``ppo/Hallway.yaml`` and ``sac/Hallway.yaml`` (memory) through the whole
system in local 2-core mode: two workers carry their agents' memories, the learner trains
on sequences, the checkpoint exports with ML-Agents' memory inputs and outputs, and a
resume or an initialization with another memory size is one line."""

from __future__ import annotations

from pathlib import Path

import onnx
import pytest
import torch
import yaml
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from driver.options import TrainOptions
from driver.training.planner import TrainingError
from driver.training.train import train
from learners.host import checkpoint
from learners.host.export import export_checkpoint

pytestmark = pytest.mark.integration

CONFIG = Path(__file__).resolve().parents[1] / "mlagents_configs" / "ppo" / "Hallway.yaml"


def options(tmp_path: Path, config: Path, **changes: object) -> TrainOptions:
    settings: dict = {
        "env": "unitysim:Hallway",
        "config": str(config),
        "results_dir": str(tmp_path),
        "run_id": "memory",
        "max_steps": 3_100,
        "workers": 2,
        "progress": False,
    }
    return TrainOptions(**(settings | changes))


def test_mlagents_hallway_config_trains_with_memory(ray_session, tmp_path):
    """Summaries every 1,000 steps; 3,100 steps are at least two updates of buffer_size
    1,024 (two workers bring 1,024 steps each at a time)."""
    data = yaml.safe_load(CONFIG.read_text())
    data["behaviors"]["Hallway"]["summary_freq"] = 1000
    config = tmp_path / "Hallway.yaml"
    config.write_text(yaml.safe_dump(data))
    result = train(options(tmp_path, config))
    assert not result.interrupted and result.steps["Hallway?team=0"] >= 3_100
    scalars = EventAccumulator(str(result.run_dir / "Hallway")).Reload().Scalars
    assert scalars("Losses/Policy Loss")  # updates on sequences ran
    assert all(e.value == e.value for e in scalars("Losses/Value Loss"))  # no NaN
    (exported,) = export_checkpoint(result.run_dir)
    model = onnx.load(str(exported))
    assert [i.name for i in model.graph.input][-1] == "recurrent_in"
    assert [o.name for o in model.graph.output][-1] == "recurrent_out"

    data["behaviors"]["Hallway"]["network_settings"]["memory"]["memory_size"] = 64
    config.write_text(yaml.safe_dump(data))
    with pytest.raises(TrainingError) as error:
        train(options(tmp_path, config, resume=True, max_steps=6_000))
    with pytest.raises(TrainingError) as started_from:
        train(options(tmp_path, config, run_id="other", initialize_from="memory"))
    for option, message in (("--resume", error), ("--initialize-from", started_from)):
        line = str(message.value)
        assert "\n" not in line
        assert line.startswith(f"{option}: Hallway was trained with network_settings.memory")
        assert "memory_size 128, the config now gives 64" in line


def test_mlagents_sac_hallway_config_trains_with_memory(ray_session, tmp_path):
    """ML-Agents' ``sac/Hallway.yaml`` unchanged but for its summaries: the replay buffer
    takes the workers' sequences and their memories, the Qs' LSTMs train, and the export
    carries the memory."""
    data = yaml.safe_load((CONFIG.parents[1] / "sac" / "Hallway.yaml").read_text())
    data["behaviors"]["Hallway"]["summary_freq"] = 1000
    config = tmp_path / "Hallway.yaml"
    config.write_text(yaml.safe_dump(data))
    result = train(options(tmp_path, config, run_id="sac", max_steps=2_100))
    assert not result.interrupted and result.steps["Hallway?team=0"] >= 2_100
    # on a loaded machine every update can come after the run's last summary (its steps
    # counted while the learner still started): the run's end writes them
    trained = checkpoint.load(result.checkpoint)["behaviors"]["Hallway?team=0"]["algorithm"]
    assert trained["gradient_steps"] > 0  # on sequences
    scalars = EventAccumulator(str(result.run_dir / "Hallway")).Reload().Scalars
    assert any(e.value > 0 for e in scalars("Policy/Gradient Steps"))  # the last ones too
    assert all(e.value == e.value for e in scalars("Losses/Q1 Loss"))  # no NaN
    assert all(bool(torch.isfinite(w).all()) for w in trained["q"].values())  # no NaN
    (exported,) = export_checkpoint(result.run_dir)
    assert [i.name for i in onnx.load(str(exported)).graph.input][-1] == "recurrent_in"
