"""Demonstration steps as a learner trains on them (behavioral cloning): each sensor's
observations, the expert's actions, and the spec and source they came with. The driver
makes them from ``.demo`` files (``demonstrations.expert_steps``) and ships them to the
learner, which checks them against the behavior's own spec before it trains on them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mlagents_envs.base_env import BehaviorSpec

from batches.specs import spec_mismatch


@dataclass(frozen=True, eq=False)
class ExpertSteps:
    source: str  # the .demo file or folder, named in every error about it
    spec: BehaviorSpec  # the recorded behavior's
    observations: tuple[np.ndarray, ...]  # per sensor, [N, *shape] float32
    continuous: np.ndarray  # [N, continuous size] float32, in Unity's range
    discrete: np.ndarray  # [N, branches] int64
    done: np.ndarray  # [N] bool: the step ended its episode (the next record is terminal)

    def __len__(self) -> int:
        return len(self.continuous)

    def problem_with(self, spec: BehaviorSpec) -> str | None:
        """A one-line reason these steps cannot train a policy of ``spec``, or None."""
        if problem := spec_mismatch(self.spec, spec):
            return f"{self.source}: {problem}"
        if not len(self):
            return f"{self.source}: fewer than two recorded steps (nothing to clone)"
        return None
