"""The core of a rollout worker: one Unity instance, a CPU copy of each behavior's policy,
and a segment builder per behavior. Plain Python (no Ray), so it runs in-process in tests;
``rollout.collecting.worker`` is the thin Ray shell around it.

Loop of one exchange: for every behavior, read the decision and terminal steps, complete
transitions, gather finished rows, ask the policy for actions (one batched call per
behavior), then step Unity. A ``collect`` call runs exchanges until enough steps of
finished rows are there, and returns them as one packed segment per behavior: how much a
call gathers is the transport's choice, independent of where rows are cut. Weights are
loaded only between ``collect`` calls. When the
player fails, partial rows are dropped (and counted), never sent, and the instance
restarts on a fresh port.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import uuid
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from mlagents_envs.base_env import ActionTuple, BehaviorSpec

from batches import specs
from batches.contracts import Actor, ActorFactory, RecurrentActor, Snapshot, Weights
from batches.parameters import Values
from batches.segment import Segment
from rollout.collecting.decisions import Decisions, allowed_mask
from rollout.collecting.horizons import Horizons
from rollout.collecting.ledger import Collected, Counts
from rollout.collecting.segments import SegmentBuilder
from rollout.environment.ports import PortAllocator
from rollout.environment.unity import (
    RECOVERABLE,
    UnityConfig,
    UnityError,
    UnityInstance,
    UnityStartError,
    UnityStartTimeout,
)

log = logging.getLogger(__name__)
NO_AGENT_STEPS = 3000  # environment steps without any agent before a run gives up on a build
SNAPSHOTS_KEPT = 16  # fixed policies (self-play opponents) kept: a window's come back


@dataclass
class BehaviorStats:
    agent_steps: int = 0
    episodes: int = 0
    return_sum: float = 0.0
    length_sum: int = 0
    rows: int = 0
    dropped_steps: int = 0
    group_episodes: int = 0  # grouped agents' episodes that ended with their group
    group_return_sum: float = 0.0  # their group rewards
    # within the agents' episodes counted in ``episodes``: group rewards, groupmates' rewards
    episode_group_sum: float = 0.0
    episode_mates_sum: float = 0.0


@dataclass
class CollectorMetrics:
    env_steps: int = 0  # exchanges with Unity
    agent_steps: int = 0  # transitions recorded, all behaviors
    restarts: int = 0
    dropped_steps: int = 0
    policy_version: int = 0
    behaviors: dict[str, BehaviorStats] = field(default_factory=dict)
    # Unity's custom statistics since the last snapshot: (value, StatsAggregationMethod)
    unity_stats: dict[str, list[tuple[float, int]]] = field(default_factory=dict)
    seconds: float = 0.0
    first_step_at: float | None = None  # wall clock (time.time) of Unity's first answer
    incarnation: str = ""  # this worker process's id: a restarted worker starts anew
    specs: dict[str, dict] = field(default_factory=dict)  # behaviors met: spec_to_dict
    snapshots_received: int = 0  # fixed policies taken in (each key once while kept)


class Collector:
    def __init__(
        self,
        unity: UnityConfig,
        actor_factory: ActorFactory,
        horizon: int | Horizons = 64,
        worker: int = 0,
        allocator: PortAllocator | None = None,
    ) -> None:
        self.unity = UnityInstance(unity, allocator)
        self.actor_factory = actor_factory
        self.horizons = Horizons.of(horizon)  # each behavior's time_horizon
        self.worker = worker
        self.builders: dict[str, SegmentBuilder] = {}
        self.actors: dict[str, Actor] = {}
        self.weights: Weights = {}
        self.version = 0
        self._snapshots: OrderedDict[str, Any] = OrderedDict()  # key -> state, oldest first
        self._loaded: dict[str, str] = {}  # behavior -> the snapshot key its actor holds
        self.metrics = CollectorMetrics(incarnation=uuid.uuid4().hex)
        self._collects = 0  # numbers this incarnation's segments (Segment.source)
        self._started = False
        self._agents_seen = False  # any agent of any behavior, ever

    # --- lifecycle ----------------------------------------------------------------------

    def start(self, restarted: bool = False) -> None:
        """A failed launch is retried as any restart is (within the restart policy) when
        this collector replaces one that died in this run (the build has worked) or when
        the player was only slow to connect; a run's first player that exits or breaks
        the protocol ends the run at once."""
        try:
            self.unity.start()
        except (UnityStartError, *RECOVERABLE) as error:
            if not (restarted or isinstance(error, UnityStartTimeout)):
                raise
            self.unity.restart(f"{type(error).__name__}: {error}")
        self.unity.reset()
        if self.metrics.first_step_at is None:
            self.metrics.first_step_at = time.time()
        self._started = True

    def close(self) -> Collected:
        """Close Unity; the last counts (rows in progress are dropped at shutdown)."""
        self.unity.close()
        self._started = False
        return Collected([], self.metrics.incarnation, self.counts())

    def load_weights(self, version: int, weights: Weights) -> None:
        """Newest published weights (between segments only); older versions are ignored."""
        if version <= self.version:
            return
        self.version, self.weights = version, weights
        for behavior, actor in self.actors.items():
            self._load(behavior, actor)
        self.metrics.policy_version = version

    def holds(self, key: str) -> bool:
        """Whether the snapshot ``key`` is here (its state need not travel again)."""
        return key in self._snapshots

    def _load(self, behavior: str, actor: Actor) -> None:
        value = self.weights.get(behavior)
        if value is None:
            return
        if not isinstance(value, Snapshot):
            actor.load_state_dict(value)
            self._loaded.pop(behavior, None)
            return
        state = self._snapshots.pop(value.key, None)
        if state is None:
            state = value.state
            self.metrics.snapshots_received += 1
        self._snapshots[value.key] = state  # the newest used last
        while len(self._snapshots) > SNAPSHOTS_KEPT:
            self._snapshots.popitem(last=False)
        if self._loaded.get(behavior) != value.key:  # the same opponent: nothing to load
            actor.load_state_dict(state)
            self._loaded[behavior] = value.key

    # --- collection ---------------------------------------------------------------------

    def collect(
        self, min_steps: int = 1, max_seconds: float | None = None, max_exchanges: int = 100_000
    ) -> Collected:
        """Step Unity until at least ``min_steps`` steps of finished rows are here (or
        ``max_seconds`` passed, or ``max_exchanges``); returns one packed segment per
        behavior that finished rows."""
        if not self._started:
            self.start()
        started = time.perf_counter()
        deadline = started + max_seconds if max_seconds is not None else None
        pieces: dict[str, list[Segment]] = {}
        steps = 0
        for _ in range(max_exchanges):
            try:
                steps += self._exchange(pieces)
            except RECOVERABLE as error:
                self._recover(error)
                continue
            if not self._agents_seen and self.metrics.env_steps >= NO_AGENT_STEPS:
                raise UnityError(
                    f"{self.unity.config.build}: no agent asked for a decision in "
                    f"{NO_AGENT_STEPS} steps: check that the agents' Behavior Type is Default "
                    "(not Heuristic Only) and that they request decisions (DecisionRequester)"
                )
            if steps >= min_steps or (deadline is not None and time.perf_counter() >= deadline):
                break
        self.metrics.seconds += time.perf_counter() - started
        self._collects += bool(pieces)  # numbered without gaps: see batches.segment.Sources
        source = (self.metrics.incarnation, self._collects)
        segments = [
            dataclasses.replace(Segment.concat(parts), source=source) for parts in pieces.values()
        ]
        return Collected(segments, self.metrics.incarnation, self.counts())

    def counts(self) -> dict[str, Counts]:
        """Per behavior, what this collector recorded and where it went (the ledger)."""
        return {
            behavior: Counts(
                b.counters.steps,
                b.counters.emitted_steps,
                b.counters.lost_steps,
                b.in_progress(),
                b.counters.reset_steps,
            )
            for behavior, b in self.builders.items()
        }

    def _exchange(self, pieces: dict[str, list[Segment]]) -> int:
        unity, steps = self.unity, 0
        for behavior, spec in unity.behavior_specs.items():
            decisions, terminals = unity.get_steps(behavior)
            builder = self.builders.get(behavior)
            if builder is None:
                if not (len(decisions) or len(terminals)):
                    continue  # no agent yet: how its sensors arrive (PNG?) is unknown
                builder = self._add_behavior(behavior, spec)
            self._agents_seen = self._agents_seen or bool(len(decisions) or len(terminals))
            builder.observe(decisions, terminals)
            finished = builder.collect(self.metrics.env_steps)
            if finished is not None:
                pieces.setdefault(behavior, []).append(finished)
                steps += len(finished)
            if len(decisions):
                chosen = self._act(behavior, spec, decisions)
                builder.act(decisions, chosen, self.version)
        unity.step()
        unity.healthy_step()
        self.metrics.env_steps += 1
        return steps

    def _add_behavior(self, behavior: str, spec: BehaviorSpec) -> SegmentBuilder:
        pixels = self.unity.png_sensors(behavior) or frozenset()
        actor = self.actor_factory(behavior, spec)
        self._load(behavior, actor)
        self.actors[behavior] = actor
        builder = SegmentBuilder(
            behavior,
            spec,
            self.horizons(behavior),
            worker=self.worker,
            pixel_sensors=pixels,
            memory_size=getattr(actor, "memory_size", 0),
        )
        self.builders[behavior] = builder
        self.metrics.specs[behavior] = specs.spec_to_dict(spec)
        self.metrics.behaviors[behavior] = BehaviorStats()
        return builder

    def _act(self, behavior: str, spec: BehaviorSpec, decisions: Any) -> Decisions:
        obs = {o.name: v for o, v in zip(spec.observation_specs, decisions.obs, strict=True)}
        branches = spec.action_spec.discrete_branches
        mask = allowed_mask(decisions, sum(branches)) if branches else None
        actor = self.actors[behavior]
        after = None
        if getattr(actor, "memory_size", 0):
            memory = self.builders[behavior].memories(decisions)
            continuous, discrete, log_prob, after = cast("RecurrentActor", actor).act_recurrent(
                obs, mask, memory
            )
        else:
            continuous, discrete, log_prob = actor.act(obs, mask)
        self.unity.set_actions(
            behavior,
            ActionTuple(continuous=actor.to_unity(continuous), discrete=discrete.astype(np.int32)),
        )
        return Decisions(continuous, discrete, log_prob, after)

    def _recover(self, error: BaseException) -> None:
        """The player failed: drop partial rows (never sent), restart on a fresh port."""
        dropped = self._drop_partial()
        self.metrics.dropped_steps += dropped
        log.warning("worker %d: Unity failed (%s); dropped %d steps", self.worker, error, dropped)
        try:
            self.unity.restart(f"{type(error).__name__}: {error}")
        finally:  # a restart whose player did not come up counts too
            self.metrics.restarts = self.unity.restarts
        self.unity.reset()

    def _drop_partial(self, lesson_reset: bool = False) -> int:
        """Every episode starts anew: rows in progress and agents' memories go (with their
        slots); the steps dropped."""
        return sum(b.drop_partial(lesson_reset) for b in self.builders.values())

    def set_parameters(self, values: Values, reset: bool) -> None:
        """A new lesson's environment parameters; ``reset``: its ``require_reset``, so that
        no episode runs on under the old values (rows in progress are dropped, as
        mlagents-learn drops them)."""
        self.unity.set_parameters(values)
        if reset and self._started:
            self.metrics.dropped_steps += self._drop_partial(lesson_reset=True)
            self.unity.reset()

    # --- metrics ------------------------------------------------------------------------

    def snapshot(self) -> CollectorMetrics:
        """Metrics so far, episode results drained into them, with the custom statistics
        Unity sent since the last snapshot (never kept here: they would grow all run)."""
        metrics = self.metrics
        metrics.agent_steps = sum(b.counters.steps for b in self.builders.values())
        for behavior, builder in self.builders.items():
            stats = metrics.behaviors[behavior]
            ended = builder.episodes.drain()
            stats.episodes += len(ended.returns)
            stats.return_sum += float(ended.returns.sum())
            stats.length_sum += int(ended.lengths.sum())
            stats.episode_group_sum += float(ended.group_rewards.sum())
            stats.episode_mates_sum += float(ended.mates_rewards.sum())
            stats.agent_steps = builder.counters.steps
            stats.rows = builder.counters.rows
            stats.dropped_steps = builder.counters.dropped_steps
            group_returns = builder.episodes.drain_group()
            stats.group_episodes += len(group_returns)
            stats.group_return_sum += float(group_returns.sum())
        stats = self.unity.drain_stats() if self.unity.env is not None else {}
        return dataclasses.replace(metrics, unity_stats=stats)  # each report: new ones only
