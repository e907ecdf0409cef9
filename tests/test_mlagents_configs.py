"""Acceptance for a user arriving from mlagents-learn: every one of ML-Agents' own example
configs that needs no demonstrations, of the examples unitysim plays (``tests/mlagents_configs/``,
unchanged; memory,
curiosity and RND included) runs on its unitysim environment in local mode
with no unsupported-feature report, no other warning and no error, for a short budget of
steps (how they learn is for the benchmarks)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import yaml

from driver.options import TrainOptions
from driver.training.train import train
from learners.trainer_config.parse import load_config
from tests.driver.test_record_demo import record
from unitysim.envs import NAMES, load

pytestmark = pytest.mark.integration

CONFIGS = Path(__file__).resolve().parent / "mlagents_configs"
TREE = sorted(CONFIGS.glob("*/*.yaml"))  # the release's whole config/ tree
# imitation/ and sac/Pyramids: their demo_path names a file of ML-Agents' repository
# (test_intrinsic_run, test_cloning_run run them on recordings)
DEMOS = (*CONFIGS.glob("imitation/*.yaml"), CONFIGS / "sac" / "Pyramids.yaml")
# the example a config is named after -> the unitysim environment that plays it
ENVIRONMENTS = {"FoodCollector": "GridFoodCollector", "PyramidsRND": "Pyramids"}


def environment(path: Path) -> str:
    name = path.stem.split("_")[0]  # 3DBall_randomize, WallJump_curriculum: their example's
    return ENVIRONMENTS.get(name, name)


FILES = [p for p in TREE if p not in DEMOS and environment(p) in NAMES]


def named(paths: list[Path]) -> list[str]:
    return [f"{p.parent.name}/{p.stem}" for p in paths]


def test_the_tree_is_the_releases_and_every_config_in_it_parses_with_nothing_unsupported():
    assert len(TREE) == 39
    for path in TREE:
        assert load_config(path).unsupported == (), path


def test_the_configs_run_here_are_those_of_the_examples_unitysim_plays():
    assert named(FILES) == [
        "poca/DungeonEscape",
        "poca/PushBlockCollab",
        "poca/SoccerTwos",
        "poca/StrikersVsGoalie",
        *(f"ppo/{n}" for n in ("3DBall", "3DBallHard", "3DBall_randomize", "Basic", "Crawler")),
        *(f"ppo/{n}" for n in ("FoodCollector", "GridWorld", "Hallway", "Match3")),
        *(f"ppo/{n}" for n in ("PushBlock", "Pyramids", "PyramidsRND", "Sorter_curriculum")),
        *(f"ppo/{n}" for n in ("Visual3DBall", "VisualFoodCollector")),
        *(f"ppo/{n}" for n in ("Walker", "WallJump", "WallJump_curriculum", "Worm")),
        *(f"sac/{n}" for n in ("3DBall", "3DBallHard", "Basic", "Crawler", "FoodCollector")),
        *(f"sac/{n}" for n in ("GridWorld", "Hallway", "PushBlock", "Walker", "WallJump")),
        "sac/Worm",
    ]
    assert not [p for p in TREE if p not in DEMOS and p not in FILES]  # every one has a stand-in


@pytest.mark.parametrize("path", FILES, ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_an_mlagents_example_config_runs_unchanged(path, ray_session, tmp_path, caplog):
    runs_unchanged(path, tmp_path, caplog)


@pytest.mark.parametrize("name", ["Crawler", "PushBlock"])
def test_an_imitation_config_runs_on_a_recording_of_the_scripted_expert(
    name, ray_session, tmp_path, caplog
):
    """ML-Agents' ``imitation/<name>.yaml`` with its ``demo_path`` (GAIL's and behavioral
    cloning's) pointing at ``record-demo --heuristic``'s recording of unitysim's expert:
    the only change."""
    demo = tmp_path / f"Expert{name}.demo"
    code, _, err = record(
        tmp_path, "--env", f"unitysim:{name}", "--heuristic", "--steps", "400", "--out", str(demo)
    )
    assert code == 0, err
    data = yaml.safe_load((CONFIGS / "imitation" / f"{name}.yaml").read_text())
    settings = data["behaviors"][name]
    assert settings["reward_signals"]["gail"]["demo_path"].endswith(demo.name)
    settings["reward_signals"]["gail"]["demo_path"] = str(demo)
    settings["behavioral_cloning"]["demo_path"] = str(demo)
    path = tmp_path / "imitation" / f"{name}.yaml"
    path.parent.mkdir()
    path.write_text(yaml.safe_dump(data))
    runs_unchanged(path, tmp_path, caplog)


def runs_unchanged(path: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """``path`` trains on its example's unitysim environment for 300 steps, saying only
    what mlagents-learn would."""
    assert load_config(path).unsupported == ()
    options = TrainOptions(
        env=f"unitysim:{environment(path)}",
        config=str(path),
        results_dir=str(tmp_path),
        run_id="example",
        max_steps=300,
        # a safety stop: the budget is the steps. A self-play pair needs two collects of
        # its time_horizon (1000 exchanges each); 60 s ran out on a loaded CI machine
        max_seconds=180,
        workers=1,
        progress=False,
    )
    with caplog.at_level(logging.WARNING):
        result = train(options)
    # every behavior of the build trains: those the file names, the others on its
    # default_settings, each said once as mlagents-learn says it (Match3's two learners)
    configured = set(load_config(path).behaviors)
    played = {b.name.split("?")[0] for b in load(environment(path)).behaviors}
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert said == [
        f"{name} is not among the behaviors of {path}: it trains with default_settings"
        for name in sorted(played - configured)
    ]
    assert not result.interrupted
    trained = {name.split("?")[0] for name in result.steps}
    assert trained == played and configured <= trained, (trained, configured)
    assert all(steps >= 300 for steps in result.steps.values()), result.steps
    if path.stem == "3DBall_randomize":  # the samplers reached the player, seeded as told
        log = (result.run_dir / "unity-logs" / "worker-0" / "Player-0.log").read_text()
        assert "environment parameter mass sampled (type 0, seed 0)" in log
        assert "environment parameter scale sampled (type 0, seed 1)" in log
