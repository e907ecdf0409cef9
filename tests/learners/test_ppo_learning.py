"""PPO learns Basic with the shipped config, and does not settle on the small goal.

With ML-Agents' ``time_horizon: 3``, PPO settles on Basic's small goal (mean return 0.07)
in some seeds, mlagents-learn's too (2 of 30 seeds, ours 4 of 30, docs/benchmarks.md);
the shipped config's horizon covers whole episodes and reached 0.9 in 30 of 30 seeds."""

from __future__ import annotations

from pathlib import Path

import pytest

from rollout.environment.ports import PortRange
from tests.helpers import train_in_process

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
BASIC_STEP_BUDGET = 30_000  # agent steps; the benchmark's seeds needed 10k-12k
SAFETY_STOP_S = 600  # only a hung run gets here; a busy machine is slower, same steps
SMALL_GOAL = 0.07  # the small goal's return: three steps of -0.01, then +0.1


@pytest.mark.integration
@pytest.mark.timeout(SAFETY_STOP_S + 60)
@pytest.mark.parametrize("seed", [0, 1])
def test_ppo_reaches_basics_large_goal_with_the_shipped_config(tmp_path, seed):
    best, history = train_in_process(
        CONFIG_DIR / "Basic.yaml",
        "unitysim:Basic",
        "Basic?team=0",
        step_budget=BASIC_STEP_BUDGET,
        goal=0.9,
        safety_stop_s=SAFETY_STOP_S,
        ports=PortRange(24650 + 10 * seed, 24659 + 10 * seed),
        registry=tmp_path / "ports",
        chunk=256,
        seed=seed,
    )
    print("(agent steps, episodes, best mean return):", history)
    verdict = "settled on the small goal" if best < SMALL_GOAL + 0.05 else "too slow"
    assert best >= 0.9, f"{verdict}; (agent steps, episodes, best mean return): {history}"


ANIMAL_STEP_BUDGET = 80_000  # agent steps; the benchmark's run passed 0.6 at about 40k


@pytest.mark.integration
@pytest.mark.timeout(SAFETY_STOP_S + 60)
def test_ppo_learns_animal_arena_from_its_84x84_camera(tmp_path):
    """The visual path end to end: PNG camera frames as uint8 through the segments, the
    simple CNN in the learner and in the worker's TorchActor. Random play returns about
    -0.4 (food found in a quarter of the 250-step episodes); 0.5 needs it found at once."""
    best, history = train_in_process(
        CONFIG_DIR / "AnimalArena.yaml",
        "unitysim:AnimalArena",
        "AnimalArena?team=0",
        step_budget=ANIMAL_STEP_BUDGET,
        goal=0.5,
        safety_stop_s=SAFETY_STOP_S,
        ports=PortRange(24690, 24699),
        registry=tmp_path / "ports",
        chunk=1024,
        min_episodes=16,
    )
    print("(agent steps, episodes, best mean return):", history)
    assert best >= 0.5, f"(agent steps, episodes, best mean return): {history}"
