"""The contracts the actor side and the learner meet at: what a worker needs of a policy
(:class:`Actor`, made per behavior by an :data:`ActorFactory`), the weights a learner
publishes (:data:`Weights`; a :class:`Snapshot` for a fixed policy), and the learner
itself (:class:`Learner`). ``rollout`` calls them and ``learners`` implements them; both
import them from here.

The service forwards each worker's segments (an ObjectRef to ``list[Segment]``, the
format of docs/batch-format.md; a ``rollout.collecting.ledger.Collected``, a list that also carries
the worker's counts for the sample ledger) with ``submit``; it keeps at most a few
submissions in flight, so a slow learner slows collection instead of growing a queue.
``submit`` returns the learner's newest weights version, and its demand: how many more
steps it wants before its next on-policy update (None: any amount, as off-policy learners
take; 0: no more at all, the run has its steps). When the version is newer than what
workers have, the service fetches ``weights()`` once (one object per version) and passes
it to every worker's next ``collect``; while the steps in flight cover the demand, it lets
idle workers wait for those weights.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from mlagents_envs.base_env import BehaviorSpec

from batches.segment import Segment


@dataclass(frozen=True)
class Snapshot:
    """A policy that never changes under its ``key`` (a self-play opponent), inside
    :data:`Weights`: a worker loads it once, however many versions carry it. ``state``: its
    state_dict, or a reference to it (a Ray ObjectRef, put once) that a worker without
    the key resolves."""

    key: str
    state: Any


Weights = dict[str, dict[str, Any] | Snapshot]  # behavior -> state_dict the actors load


def base_name(behavior: str) -> str:
    """``3DBall?team=0`` -> ``3DBall``: trainer configs name behaviors without the team."""
    return behavior.split("?", 1)[0]


class Actor(Protocol):
    """What a worker needs of a policy (``learners.acting.numpy_policy.NumpyActor`` is one): numpy
    observations per sensor and an allowed-mask in; continuous [n, c], discrete
    [n, branches] and log-probabilities [n, c + branches] (one per action component) out;
    and the continuous action Unity gets for a chosen one (the policy's convention:
    ML-Agents' scale the Gaussian's sample)."""

    def act(
        self, obs: dict[str, np.ndarray], mask: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def to_unity(self, continuous: np.ndarray) -> np.ndarray: ...

    def load_state_dict(self, state: Mapping[str, Any]) -> Any: ...


class RecurrentActor(Actor, Protocol):
    """An actor whose policy has memory (``memory_size`` > 0): it acts from each agent's
    memory ``[n, memory_size]`` and gives the next one last (``rollout.collecting.segments``)."""

    @property
    def memory_size(self) -> int: ...

    def act_recurrent(
        self, obs: dict[str, np.ndarray], mask: np.ndarray | None, memory: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]: ...


ActorFactory = Callable[[str, BehaviorSpec], Actor]  # (behavior name, spec) -> policy


class Learner(Protocol):
    def submit(self, segments: list[Segment]) -> tuple[int, int | None]:
        """Consume segments; return the newest weights version and the demand."""
        ...

    def weights(self) -> tuple[int, Weights]:
        """The newest version and its weights, behavior -> state_dict."""
        ...
