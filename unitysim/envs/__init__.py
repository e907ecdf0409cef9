"""The environments unitysim can play, by the name used for launchers and ``--env``.

Entries are loaded lazily so that a player imports only the environment it runs.
"""

from __future__ import annotations

import importlib

from unitysim.envs.base import SimEnv

_ENTRIES: dict[str, str] = {
    # learnable, with dynamics close to the originals
    "3DBall": "unitysim.envs.ball3d:Ball3D",
    "3DBallHard": "unitysim.envs.ball3d:Ball3DHard",
    "Visual3DBall": "unitysim.envs.ball3d:Visual3DBall",
    "Basic": "unitysim.envs.basic:Basic",
    "GridWorld": "unitysim.envs.gridworld:GridWorld",
    # a first-person camera over walled arenas with food, AnimalAI-like
    "AnimalArena": "unitysim.envs.animal_arena:AnimalArena",
    # spec-faithful to the reference dumps, with simple learnable rewards
    "StrikersVsGoalie": "unitysim.envs.strikers:StrikersVsGoalie",
    "SoccerTwos": "unitysim.envs.soccer:SoccerTwos",
    "Walker": "unitysim.envs.walker:Walker",
    "Crawler": "unitysim.envs.crawlers:Crawler",
    "Worm": "unitysim.envs.crawlers:Worm",
    "Hallway": "unitysim.envs.hallway:Hallway",
    "Pyramids": "unitysim.envs.pyramids:Pyramids",
    "DungeonEscape": "unitysim.envs.dungeon:DungeonEscape",
    "GridFoodCollector": "unitysim.envs.food_collector:GridFoodCollector",
    "VisualFoodCollector": "unitysim.envs.food_collector:VisualFoodCollector",
    "WallJump": "unitysim.envs.walljump:WallJump",
    "PushBlock": "unitysim.envs.push_block:PushBlock",
    "PushBlockCollab": "unitysim.envs.push_block:PushBlockCollab",
    # a BufferSensor (variable-length observations), laid out as the example
    "Sorter": "unitysim.envs.sorter:Sorter",
    # masked moves on a board of pieces, vector and PNG-compressed multi-channel observations
    "Match3": "unitysim.envs.match3:Match3",
    # for tests of the rollout side: echoes each agent's last action into its observation
    "Echo": "unitysim.envs.echo:Echo",
}

NAMES: tuple[str, ...] = tuple(_ENTRIES)


def load(name: str) -> type[SimEnv]:
    """The environment class for ``name`` (case-sensitive, as in the examples)."""
    try:
        module_name, class_name = _ENTRIES[name].split(":")
    except KeyError:
        raise ValueError(
            f"unknown unitysim environment {name!r}; choose one of: {', '.join(NAMES)}"
        ) from None
    env_class = getattr(importlib.import_module(module_name), class_name)
    assert env_class.name == name, f"{_ENTRIES[name]} declares name {env_class.name!r}"
    return env_class
