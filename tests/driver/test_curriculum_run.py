"""Environment parameters end to end, in local 2-core mode: ML-Agents' own
``WallJump_curriculum.yaml`` (its lessons shortened to 5 episodes, its summaries to every
2,000 steps) moves both walls through every lesson, each worker's player receives each
lesson's values with a stream of its own, the lesson numbers reach TensorBoard and the
checkpoint, and ``--resume`` goes on in the last lesson (``3DBall_randomize.yaml``'s
samplers: ``tests/test_mlagents_configs.py``)."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
import yaml
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from driver.options import TrainOptions
from driver.training.train import train
from learners.host import checkpoint

pytestmark = pytest.mark.integration

CONFIGS = Path(__file__).resolve().parents[1] / "mlagents_configs" / "ppo"


def player_lines(run_dir: Path, worker: int) -> list[str]:
    """What the worker's player said of the environment parameters it received."""
    text = (run_dir / "unity-logs" / f"worker-{worker}" / "Player-0.log").read_text()
    return re.findall(r"environment parameter (.*)", text)


def lesson_numbers(run_dir: Path, behavior: str) -> dict[str, list[float]]:
    events = EventAccumulator(str(run_dir / behavior)).Reload()
    prefix = "Environment/Lesson Number/"
    return {
        tag[len(prefix) :]: [e.value for e in events.Scalars(tag)]
        for tag in events.Tags()["scalars"]
        if tag.startswith(prefix)
    }


def test_walljumps_curriculum_moves_both_walls_through_every_lesson(ray_session, tmp_path):
    config = yaml.safe_load((CONFIGS / "WallJump_curriculum.yaml").read_text())
    for parameter in config["environment_parameters"].values():
        for lesson in parameter["curriculum"][:-1]:
            lesson["completion_criteria"]["min_lesson_length"] = 5
    for behavior in config["behaviors"].values():
        behavior["summary_freq"] = 2000
    path = tmp_path / "WallJump_curriculum.yaml"
    path.write_text(yaml.safe_dump(config))
    options = TrainOptions(
        env="unitysim:WallJump",
        config=str(path),
        results_dir=str(tmp_path / "results"),
        run_id="walls",
        max_steps=8_000,  # progress 0.5 (the last threshold) at 4,000 steps of each behavior
        progress=False,
    )
    result = train(options)
    for worker, seed in ((0, 0), (1, 1000)):
        said = player_lines(result.run_dir, worker)
        # lesson 0, then the newest lessons at each collect (a worker may skip one, and the
        # last change may come after its last collect): the samplers' seeds are the run's
        # (0) plus one per sampler in the file's order (big 0, 1, 2), moved by 1000 per worker
        assert said[:2] == [
            f"big_wall_height sampled (type 0, seed {seed})",
            "small_wall_height = 1.5",
        ]
        assert len(said) > 2, f"worker {worker} never received a later lesson"
        sampled = {
            int(m) for m in re.findall(r"big_wall_height sampled .*seed (\d+)", "\n".join(said))
        }
        assert sampled <= {seed, seed + 1, seed + 2}
        smalls = [float(v) for v in re.findall(r"small_wall_height = ([\d.]+)", "\n".join(said))]
        assert smalls == sorted(smalls), "lessons only go up"
    state = checkpoint.load(result.checkpoint)
    assert state["meta"]["lessons"] == {"big_wall_height": 3, "small_wall_height": 3}
    seen = lesson_numbers(result.run_dir, "SmallWallJump")
    assert set(seen) == {"big_wall_height", "small_wall_height"}
    assert seen["small_wall_height"] == sorted(seen["small_wall_height"])  # lessons only go up

    resumed = train(dataclasses.replace(options, resume=True, max_steps=8_500))
    assert checkpoint.load(resumed.checkpoint)["meta"]["lessons"] == state["meta"]["lessons"]
    for worker in (0, 1):  # the players of the resumed run start in the last lessons
        assert set(player_lines(resumed.run_dir, worker)[:2]) == {
            "big_wall_height = 8.0",
            "small_wall_height = 4.0",
        }
