"""A ``.demo`` file (or folder) as the steps a learner clones (``batches.expert_steps``),
paired as ML-Agents' ``demo_to_buffer`` pairs them: each record but the last, its
observations with the action stored in the same record. Unity's recorder stores there
the action that led to the step (``record-demo --actions unity`` does too), so the pairs
are those mlagents-learn trains on from the same file."""

from __future__ import annotations

import os

import numpy as np

from batches.expert_steps import ExpertSteps
from demonstrations.demo_file import read_demo


def expert_steps(path: str | os.PathLike[str]) -> ExpertSteps:
    """The demonstration at ``path``; ``DemoError`` names the file when it cannot be read."""
    demo = read_demo(path)
    spec, steps = demo.behavior_spec, demo.steps[:-1]
    actions = spec.action_spec
    observations = tuple(
        np.stack([s.observations[i] for s in steps]).astype(np.float32, copy=False)
        if steps
        else np.zeros((0, *sensor.shape), np.float32)
        for i, sensor in enumerate(spec.observation_specs)
    )
    continuous = np.zeros((len(steps), actions.continuous_size), np.float32)
    discrete = np.zeros((len(steps), len(actions.discrete_branches)), np.int64)
    for row, step in enumerate(steps):  # a record without an action keeps zeros
        picked = step.continuous[: actions.continuous_size]
        continuous[row, : len(picked)] = picked
        chosen = step.discrete[: len(actions.discrete_branches)]
        discrete[row, : len(chosen)] = chosen
    done = np.array([s.done for s in demo.steps[1:]], dtype=bool)
    return ExpertSteps(str(path), spec, observations, continuous, discrete, done)
