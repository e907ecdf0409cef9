"""The central learner as a Ray actor, defined without torch: the driver that starts it
(``driver.training.train``) never loads torch (1.3 s of CPU while Ray starts); the actor's own
process does, on a thread, while it already takes segments.

Why the thread: the learner's process needs seconds of CPU for torch, tensordict and
torchrl before it can build a network. Workers need none of them and step Unity a second
after Ray is up; had the learner's actor answered nothing until then, the service would
hold them back (it keeps a few submissions in flight), and the first summary would wait
for the learner's imports. So ``LearnerHost`` answers at once: until its
``CentralLearner`` is built it keeps what arrives (each source once), counts its steps
for ``progress``, and states an on-policy behavior's demand from the config. A submission
that fills that demand, or the run's steps, waits for the learner and hands everything
over in order: the run is not done before the learner has trained on its steps.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from batches import keys
from batches.contracts import Snapshot, Weights
from batches.segment import Segment, Sources
from learners.host.counters import LearnerStats, demand, on_policy_wanted
from learners.trainer_config.trainer_types import trainer

if TYPE_CHECKING:
    from tensordict import TensorDict

    from batches.expert_steps import ExpertSteps
    from learners.host.learner import CentralLearner
    from learners.trainer_config.settings import RunConfig


BUILD_NICENESS = 10  # added to the building thread's: its imports wait for idle CPU


class LearnerHost:
    """Holds a ``learners.host.learner.CentralLearner`` (the contract of
    ``batches/contracts.py``) in the actor's process; builds it on a thread."""

    def __init__(
        self,
        config: RunConfig,
        max_steps: int | None,
        torch_threads: int | None,
        seed: int,
        device: str = "cpu",
        mixed_precision: bool = False,
        inference: bool = False,
        experts: Mapping[str, ExpertSteps] | None = None,
    ) -> None:
        self.config = config
        self.max_steps = max_steps
        self.inference = inference
        self._learner: CentralLearner | None = None
        self._error: BaseException | None = None
        self._built = threading.Event()
        self._lock = threading.Lock()  # the learner's data: submits, flushes, state
        self._early: list[Any] = []  # segments taken before the learner was built
        self._early_steps: dict[str, int] = {}  # their steps per behavior
        self._sources = Sources()
        self._early_duplicates = 0
        self._builder = threading.Thread(
            target=self._build,
            args=(
                config,
                max_steps,
                torch_threads,
                seed,
                device,
                mixed_precision,
                inference,
                experts,
            ),
            daemon=True,
        )
        self._builder.start()

    def _build(self, *args: Any) -> None:
        # Yield the CPU to the workers and their players while they collect the first
        # update's data (this thread only; it ends once the learner is built).
        with contextlib.suppress(OSError, AttributeError):
            thread = threading.get_native_id()
            niceness = os.getpriority(os.PRIO_PROCESS, thread) + BUILD_NICENESS
            os.setpriority(os.PRIO_PROCESS, thread, niceness)
        try:
            from learners.host.devices import Compute
            from learners.host.learner import CentralLearner

            config, max_steps, threads, seed, device, mixed_precision, inference, experts = args
            compute = Compute.of(device, mixed_precision)
            learner = CentralLearner(config, max_steps, threads, seed, compute, inference, experts)
            learner.prepare()  # the algorithms' modules (torchrl) before the first data
            self._learner = learner
        except BaseException as error:  # raised by the next call that needs the learner
            self._error = error
        self._built.set()

    @property
    def learner(self) -> CentralLearner:
        """The built learner, with what came before it handed over (waits for both)."""
        self._built.wait()
        if self._error is not None:
            raise RuntimeError(f"the learner failed to start: {self._error}") from self._error
        assert self._learner is not None
        self._learner.stats.duplicate_steps += self._early_duplicates
        self._early_duplicates = 0
        if self._early:
            early, self._early = self._early, []
            for segment in early:  # one by one: progress counts each as it moves over
                if (behavior := _behavior(segment)) in self._early_steps:
                    self._early_steps[behavior] -= len(segment)
                self._learner.submit([segment])
        return self._learner

    def prepare(self) -> None:
        """Wait until the learner is built (its imports are done)."""
        with self._lock:
            self.learner  # noqa: B018  (the property waits and hands over)

    def submit(self, segments: list[Any]) -> tuple[int, int | None]:
        with self._lock:
            if not self._built.is_set():
                self._keep_early(segments)
                wanted = self._early_wanted()
                if wanted is None or wanted > 1:  # no update due, and the run goes on
                    return 0, wanted
                # an update is due, or the run has its steps: the learner trains on them
                # all before the run may end (a short SAC run once ended untrained)
                segments = []  # kept: handed over with the others, once the learner is up
            return self.learner.submit(segments)

    def _keep_early(self, segments: list[Any]) -> None:
        for segment in segments:
            sourced = isinstance(segment, Segment) and segment.source is not None
            if sourced and not self._sources.first(segment):
                self._early_duplicates += len(segment)  # a delivery Ray retried
                continue
            self._early.append(segment)
            behavior = _behavior(segment)
            if self.config.for_behavior(behavior).self_play is not None:
                continue  # which of its steps count (the learning team's) is for the learner
            self._early_steps[behavior] = self._early_steps.get(behavior, 0) + len(segment)

    def _early_wanted(self) -> int | None:
        """The on-policy demand of the behaviors seen so far, from their configs, as
        ``CentralLearner.wanted`` bounds it."""
        wants = [
            on_policy_wanted(settings.hyperparameters.buffer_size, steps)
            for behavior, steps in self._early_steps.items()
            if trainer(settings := self.config.for_behavior(behavior)).waits_for_fresh_data
        ]
        return demand(self._early_steps, self.config, self.max_steps, wants, self.inference)

    def meet(self, specs: dict[str, dict[str, Any]]) -> None:
        """Behaviors the workers saw: their steps count from 0 at once, then the learner
        (once built) trains each of them."""
        with self._lock:
            if not self._built.is_set():
                for behavior in specs:
                    if self.config.for_behavior(behavior).self_play is None:
                        self._early_steps.setdefault(behavior, 0)
            self.learner.meet(specs)

    def weights(self) -> tuple[int, dict[str, Any]]:
        with self._lock:
            return self.learner.weights()

    def progress(self) -> dict[str, Any]:
        """Steps per behavior, those not yet handed over included."""
        if self._learner is None:  # never done: the learner has yet to train on them
            steps = dict(self._early_steps)
            return {
                "version": 0,
                "steps": steps,
                "done": False,
                "stats": LearnerStats(),
                "notes": [],
            }
        progress = self._learner.progress()
        for behavior, steps in list(self._early_steps.items()):
            progress["steps"][behavior] = progress["steps"].get(behavior, 0) + steps
        return progress

    def drain_reports(self) -> list[tuple[str, int, dict[str, float]]]:
        return self._learner.drain_reports() if self._learner is not None else []

    def state_dict(self, behaviors: list[str] | None = None) -> dict[str, Any]:
        with self._lock:
            return self.learner.state_dict(behaviors)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        with self._lock:
            self.learner.load_state_dict(state)

    def initialize(self, state: dict[str, Any]) -> None:
        with self._lock:
            self.learner.initialize(state)


def _behavior(segment: Segment | TensorDict) -> str:
    """A segment's behavior: a worker's ``Segment``, or a TensorDict (tests, benchmarks)."""
    if isinstance(segment, Segment):
        return segment.behavior
    return str(segment.get_non_tensor(keys.BEHAVIOR))


def learner_actor(
    config: RunConfig,
    max_steps: int | None = None,
    num_cpus: float = 0,
    torch_threads: int | None = 1,
    seed: int = 0,
    device: str = "cpu",
    mixed_precision: bool = False,
    inference: bool = False,
    experts: Mapping[str, ExpertSteps] | None = None,
) -> Any:
    """Start the learner as a Ray actor (Ray imported here: the class itself needs none).
    ``device`` other than cpu: the actor asks Ray for one GPU (``learners.host.devices``'s
    ``learner_device`` decides, in the driver, whether it should).

    ``progress`` and ``drain_reports`` answer on a thread of their own: the driver's
    summaries and checks do not wait for an update in progress (mlagents-learn writes a
    summary before the update that follows it, too)."""
    import ray

    class RayLearner(LearnerHost):
        progress = ray.method(concurrency_group="status")(LearnerHost.progress)
        drain_reports = ray.method(concurrency_group="status")(LearnerHost.drain_reports)

        def __init__(self, *args: Any) -> None:
            super().__init__(*args)
            self._snapshot_refs: dict[str, ray.ObjectRef] = {}

        def weights(self) -> tuple[int, Weights]:
            """Each snapshot put once: the weights carry its reference, which a worker
            resolves only if it lacks the snapshot's key."""
            with self._lock:
                version, weights = self.learner.weights()
                live = self.learner.self_play.snapshot_keys()  # a window's may come back
            out = dict(weights)
            for behavior, value in weights.items():
                if isinstance(value, Snapshot):
                    if value.key not in self._snapshot_refs:
                        self._snapshot_refs[value.key] = ray.put(value.state)
                    out[behavior] = Snapshot(value.key, self._snapshot_refs[value.key])
            self._snapshot_refs = {k: r for k, r in self._snapshot_refs.items() if k in live}
            return version, out

    remote = ray.remote(concurrency_groups={"status": 1})(RayLearner)
    remote = remote.options(num_cpus=num_cpus, num_gpus=0 if device == "cpu" else 1)
    return remote.remote(
        config, max_steps, torch_threads, seed, device, mixed_precision, inference, experts
    )
