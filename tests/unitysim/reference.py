"""Reads ``data/reference-behavior-specs.md``: dumps of real example builds' behavior specs
and first ``get_steps()``, printed through mlagents_envs (the ground truth for unitysim)."""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass, field
from pathlib import Path

DUMP = Path(__file__).parent / "data" / "reference-behavior-specs.md"


@dataclass
class Sensor:
    name: str = ""
    shape: tuple[int, ...] = ()
    dimension_property: tuple[int, ...] = ()
    observation_type: str = ""


@dataclass
class Steps:
    agent_id: list[int] = field(default_factory=list)
    group_id: list[int] = field(default_factory=list)
    observation_shapes: list[tuple[int, ...]] = field(default_factory=list)
    action_mask_shapes: list[tuple[int, ...]] | None = None


@dataclass
class Behavior:
    name: str
    sensors: list[Sensor] = field(default_factory=list)
    continuous: int = 0
    branches: tuple[int, ...] = ()
    decision: Steps = field(default_factory=Steps)
    terminal: Steps = field(default_factory=Steps)


def _ints(text: str) -> list[int]:
    return [int(v) for v in re.findall(r"-?\d+", text)]


def parse(text: str) -> dict[str, dict[str, Behavior]]:
    """``{environment: {behavior name: Behavior}}`` in the dump's order."""
    envs: dict[str, dict[str, Behavior]] = {}
    specs_text = text.split("## Problems seen")[0]
    for section in re.split(r"^### ", specs_text, flags=re.M)[1:]:
        title, _, body = section.partition("\n")
        block = body.split("```")[1]
        specs_part, _, steps_part = block.partition("current steps:")
        behaviors: dict[str, Behavior] = {}
        for chunk in re.split(r"behavior_name: ", specs_part)[1:]:
            name = chunk.split("\n", 1)[0].strip()
            behavior = Behavior(name)
            for sensor_text in re.split(r"observation_spec\[\d+\]:", chunk)[1:]:
                fields = dict(re.findall(r"^\s*(\w+): (.*)$", sensor_text, flags=re.M))
                behavior.sensors.append(
                    Sensor(
                        name=fields["name"],
                        shape=tuple(ast.literal_eval(fields["shape"])),
                        dimension_property=tuple(
                            int(v) for v in re.findall(r": (\d+)>", fields["dimension_property"])
                        ),
                        observation_type=fields["observation_type"].split(".")[-1],
                    )
                )
            action = re.search(r"action_spec: Continuous: (\d+), Discrete: \(([^)]*)\)", chunk)
            behavior.continuous = int(action.group(1))
            behavior.branches = tuple(_ints(action.group(2)))
            behaviors[name] = behavior
        for chunk in re.split(r"behavior_name: ", steps_part)[1:]:
            name = chunk.split("\n", 1)[0].strip()
            decision_text, _, terminal_text = chunk.partition("terminal step:")
            for steps, part in (
                (behaviors[name].decision, decision_text),
                (behaviors[name].terminal, terminal_text),
            ):
                ids = re.search(r"agent_id: \[([^\]]*)\]", part, flags=re.S)
                steps.agent_id = _ints(ids.group(1))
                steps.group_id = _ints(re.search(r"group_id: \[([^\]]*)\]", part).group(1))
                shapes = re.search(r"observation_shapes: (\[.*\])", part).group(1)
                steps.observation_shapes = [tuple(s) for s in ast.literal_eval(shapes)]
                masks = re.search(r"action_mask_shapes: (\[.*\])", part)
                if masks:
                    steps.action_mask_shapes = [tuple(s) for s in ast.literal_eval(masks.group(1))]
        envs[title.strip()] = behaviors
    return envs


REFERENCE = parse(DUMP.read_text())
