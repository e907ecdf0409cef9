"""Ray Tune's PBT without its fairness pauses where every trial runs at once.

In asynchronous mode, Ray's ``PopulationBasedTraining`` pauses a trial that reaches a
perturbation while any other trial is paused or pending, so that trials waiting for the
cluster get their turn. A trial that has just exploited is paused too, for an instant,
before it restarts from its new checkpoint; so every exploit also paused whichever trials
reached a perturbation meanwhile. For a run, a pause is a whole stretch: a final
checkpoint, its workers, Unity instances and learner stopped, then all started again from
that checkpoint (4 trials on 2 cores, 8,000 steps each: 11 stretches, 4 of them such
pauses; docs/tune.md). Where every trial has its resources at once, nothing waits for a
turn, and those trials go on instead.
"""

from __future__ import annotations

from typing import Any

from ray.tune.experiment import Trial
from ray.tune.schedulers import PopulationBasedTraining, TrialScheduler


class AllAtOncePBT(PopulationBasedTraining):
    """PBT for a population that runs at once: a trial is paused only to exploit."""

    def on_trial_result(self, tune_controller: Any, trial: Trial, result: dict) -> str:
        decision = super().on_trial_result(tune_controller, trial, result)
        if decision == TrialScheduler.PAUSE and trial.status == Trial.RUNNING:
            return TrialScheduler.CONTINUE  # a turn for others: none waits for one
        return decision
