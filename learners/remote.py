"""The central learner as a Ray actor, defined without torch: the driver that starts it
(``rollout.train``) never loads torch (1.3 s of CPU while Ray starts); the actor's own
process does, in ``__init__``."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from learners.config import RunConfig


class LearnerHost:
    """Holds a ``learners.learner.CentralLearner`` (the contract of
    ``rollout/learner_api.py``) in the actor's process."""

    def __init__(
        self,
        config: RunConfig,
        max_steps: int | None,
        torch_threads: int | None,
        seed: int,
        device: str = "cpu",
        mixed_precision: bool = False,
    ) -> None:
        from learners.devices import Compute
        from learners.learner import CentralLearner

        compute = Compute.of(device, mixed_precision)
        self.learner = CentralLearner(config, max_steps, torch_threads, seed, compute)

    def prepare(self) -> None:
        self.learner.prepare()

    def submit(self, segments: list[Any]) -> tuple[int, int | None]:
        return self.learner.submit(segments)

    def weights(self) -> tuple[int, dict[str, Any]]:
        return self.learner.weights()

    def progress(self) -> dict[str, Any]:
        return self.learner.progress()

    def drain_reports(self) -> list[tuple[str, int, dict[str, float]]]:
        return self.learner.drain_reports()

    def state_dict(self) -> dict[str, Any]:
        return self.learner.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.learner.load_state_dict(state)


def learner_actor(
    config: RunConfig,
    max_steps: int | None = None,
    num_cpus: float = 0,
    seed: int = 0,
    device: str = "cpu",
    mixed_precision: bool = False,
) -> Any:
    """Start the learner as a Ray actor (Ray imported here: the class itself needs none).
    ``device`` other than cpu: the actor asks Ray for one GPU (``learners.devices``'s
    ``learner_device`` decides, in the driver, whether it should).

    ``progress`` and ``drain_reports`` answer on a thread of their own: the driver's
    summaries and checks do not wait for an update in progress (mlagents-learn writes a
    summary before the update that follows it, too)."""
    import ray

    class RayLearner(LearnerHost):
        progress = ray.method(concurrency_group="status")(LearnerHost.progress)
        drain_reports = ray.method(concurrency_group="status")(LearnerHost.drain_reports)

    remote = ray.remote(concurrency_groups={"status": 1})(RayLearner)
    remote = remote.options(num_cpus=num_cpus, num_gpus=0 if device == "cpu" else 1)
    learner = remote.remote(config, max_steps, 1, seed, device, mixed_precision)
    learner.prepare.remote()  # while the workers start
    return learner
