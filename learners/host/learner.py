"""The central learner: one network and one algorithm per behavior, weights by version.

Implements the contract of ``batches/contracts.py`` (``submit`` segments, ``weights``)
as a plain class, so every algorithm runs and is tested without Ray; ``learner_actor``
is the Ray shell the CLI starts. Behaviors are discovered from the segments themselves
(each carries its ``BehaviorSpec`` as a dict), and built with the same
``PolicyFactory`` the workers use, so learner and worker networks always match.

Versions: one global counter, bumped by every update of any behavior (and by every
change of what a self-play team acts with, and by networks loaded from another run).
Policy lag of a step is counted in updates *of its own behavior* since the version that
acted, so two behaviors learning side by side do not make each other's data look stale.

Self-play (``learners/algorithms/self_play.py``): the teams of a brain with a ``self_play`` section
share one behavior state (keyed by the first team seen); only the steps the learning
policy acted reach its algorithm, and each team's weights are the learning policy's or
its opponent snapshot.
"""

from __future__ import annotations

import time
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Protocol

import torch

from batches import keys
from batches.contracts import Weights, base_name
from batches.expert_steps import ExpertSteps
from batches.segment import Segment, Sources
from batches.specs import spec_from_dict
from learners.acting.factory import policy_factory
from learners.algorithms.self_play import SelfPlay, as_brain, learning_steps, team_of
from learners.algorithms.trajectory_store import BufferTooLarge
from learners.algorithms.update_cut import update_cut
from learners.host import checkpoint
from learners.host.counters import LearnerStats, all_done, budget, demand
from learners.host.devices import Compute, to_cpu, usable_cores
from learners.networks.policies import ActorCritic, numpy_state
from learners.reward_signals.cloning import BehavioralCloning
from learners.trainer_config.trainer_types import trainer

if TYPE_CHECKING:  # tensordict only where segments arrive: the driver never loads it
    from tensordict import TensorDict

    from learners.trainer_config.settings import RunConfig, TrainerSettings


class Algorithm(Protocol):
    """What ``learners/algorithms/ppo.py``, ``sac.py`` and ``impala.py`` each provide."""

    network: ActorCritic

    def add(self, segment: TensorDict, lag: torch.Tensor) -> int: ...
    def ready(self) -> bool: ...
    def wanted(self) -> int | None: ...  # on-policy: steps missing before the next update
    def update(self, progress: float) -> dict[str, float]: ...
    def state_dict(self) -> dict[str, Any]: ...
    def load_state_dict(self, state: dict[str, Any]) -> None: ...


def make_algorithm(
    network: ActorCritic,
    settings: TrainerSettings,
    compute: Compute | None = None,
    experts: Mapping[str, ExpertSteps] | None = None,
) -> Algorithm:
    """The behavior's algorithm, on ``compute``'s device (the network must be there);
    ``experts``: gail's demonstrations (PPO's and SAC's reward signals)."""
    algorithm = trainer(settings).algorithm_class(settings.network_settings.memory is not None)
    if settings.reward_signals:
        return algorithm(network, settings, compute or Compute(), experts=experts)
    return algorithm(network, settings, compute or Compute())


def policy_lag(updates: list[int], acted: torch.Tensor) -> torch.Tensor:
    """Per step: how many of the behavior's own updates (their global versions, ascending)
    came after the version that acted."""
    made = torch.tensor(updates, dtype=torch.int64, device=acted.device)
    return len(made) - torch.searchsorted(made, acted.contiguous(), right=True)


@dataclass
class BehaviorState:
    spec: dict[str, Any]
    settings: TrainerSettings
    network: ActorCritic
    algorithm: Algorithm
    steps: int = 0  # agent steps received (ML-Agents' "Step")
    updates: list[int] = field(default_factory=list)  # global versions this behavior made
    cloning: BehavioralCloning | None = None  # behavioral_cloning, after each update


class CentralLearner:
    def __init__(
        self,
        config: RunConfig,
        max_steps: int | None = None,
        torch_threads: int | None = None,
        seed: int = 0,
        compute: Compute | None = None,
        inference: bool = False,
        experts: Mapping[str, ExpertSteps] | None = None,
    ) -> None:
        """``experts``: the demonstrations of ``behavioral_cloning``, by ``demo_path``;
        ``torch_threads`` 0: every core this process may keep busy (``usable_cores``; None:
        torch's choice)."""
        if torch_threads is not None:  # the Ray actor shares its node with Unity workers
            torch.set_num_threads(torch_threads or usable_cores())
        self.compute = compute or Compute()
        self.config = config
        self.max_steps = max_steps  # stop earlier than max_steps (CLI --max-steps)
        self.inference = inference  # count the steps, train on none (CLI --inference)
        self.experts = dict(experts or {})
        self.factory = policy_factory(config, seed)
        self.version = 0
        self.behaviors: dict[str, BehaviorState] = {}
        self.stats = LearnerStats()
        self._updating_since: float | None = None  # perf_counter when the update under way began
        self._sources = Sources()
        self._reports: list[tuple[str, int, dict[str, float]]] = []
        self._published: tuple[int, Weights] | None = None
        self.self_play = SelfPlay(seed)
        self._keys: dict[str, str] = {}  # behavior id -> its state's key (self-play: shared)

    def prepare(self) -> None:
        """Load the algorithms' modules (torchrl, tensordict: seconds of CPU) before the
        first data arrives, not while the first update waits on them."""
        for settings in (*self.config.behaviors.values(), self.config.default):
            trainer(settings).algorithm_class()

    # --- the learner contract -----------------------------------------------------------

    def submit(self, segments: list[Segment | TensorDict]) -> tuple[int, int | None]:
        """Take segments (as workers send them, or already TensorDicts), update behaviors
        whose data is ready; the newest version and the demand (``batches/contracts.py``)."""
        started = time.perf_counter()
        for segment in segments:
            if isinstance(segment, Segment):
                if segment.source is not None and not self._sources.first(segment):
                    self.stats.duplicate_steps += len(segment)  # a retried delivery
                    continue
                segment = segment.to_tensordict()
            behavior = segment.get_non_tensor(keys.BEHAVIOR)
            state = self._behavior(behavior, segment.get_non_tensor(keys.SPEC))
            key = self._keys[behavior]
            if state.settings.self_play is not None:
                segment = self._learning_part(behavior, state, segment)
            if segment is not None and len(segment):
                self._learn(key, state, segment)
            if state.settings.self_play is not None:
                current = lambda s=state: numpy_state(s.network)  # noqa: E731
                finished = state.steps >= budget(key, self.config, self.max_steps)
                brain, version = base_name(key), self.version + 1
                if self.self_play.advance(brain, state.steps, version, current, finished):
                    self.version += 1
        self.stats.submit_seconds += time.perf_counter() - started
        return self.version, self.wanted()

    def _learn(self, key: str, state: BehaviorState, segment: TensorDict) -> None:
        """Store ``segment``, updating where the buffer tips over
        (``learners/algorithms/update_cut.py``): its steps after that wait for the next update, as
        later arrivals do in ML-Agents."""
        while not self.inference and (wanted := state.algorithm.wanted()) is not None:
            cut = update_cut(segment, wanted)
            if cut >= len(segment):
                break
            self._store(key, state, segment[:cut])
            segment = segment[cut:]
        self._store(key, state, segment)

    def _store(self, key: str, state: BehaviorState, segment: TensorDict) -> None:
        lag = policy_lag(state.updates, segment[keys.POLICY_VERSION])
        spent = state.steps >= budget(key, self.config, self.max_steps)
        state.steps += segment.batch_size[0]
        if self.inference:
            return
        try:
            state.algorithm.add(segment, lag)
        except BufferTooLarge as error:  # before the buffer exists: one line, no OOM kill
            raise MemoryError(f"behavior {base_name(key)}: {error}") from None
        if state.algorithm.ready() and not spent:  # past its steps: no more updates
            self._update(key, state)

    def _learning_part(
        self, behavior: str, state: BehaviorState, segment: TensorDict
    ) -> TensorDict | None:
        """Self-play: the steps of ``segment`` the learning policy acted (the others count
        as the brain's ghost steps), under the brain's sensor names; their finished games
        move the ELO."""
        brain, team = base_name(behavior), team_of(behavior)
        learning = self.self_play.learning(team, segment[keys.POLICY_VERSION])
        self.self_play.ghosts[brain].ghost_steps += int((~learning).sum())
        if not bool(learning.any()):
            return None
        self.self_play.record_games(brain, segment, learning)
        return as_brain(learning_steps(segment, learning), state.network.sensor_names)

    def meet(self, specs: dict[str, dict[str, Any]]) -> None:
        """Behaviors the workers saw (``{behavior: spec dict}``), before any of their rows
        arrive. Each is trained from then on, as mlagents-learn makes a trainer when a
        behavior appears: the run is not done while one of them lacks its steps, and a
        self-play team joins its controller's turns (a behavior's first row may take a long
        ``time_horizon`` to come)."""
        for behavior, spec in specs.items():
            self._behavior(behavior, spec)

    def wanted(self) -> int | None:
        """Steps before the next on-policy update of any behavior (None: no such behavior),
        and never more than the run still needs (0: it has them all). The service holds
        workers back beyond it, so that update trains on fresh data, and the run stops
        within a collect of its ``max_steps``."""
        steps = {name: s.steps for name, s in self.behaviors.items()}
        wants = [w for s in self.behaviors.values() if (w := s.algorithm.wanted()) is not None]
        return demand(steps, self.config, self.max_steps, wants, self.inference)

    def weights(self) -> tuple[int, Weights]:
        """Numpy weights (a worker loads them without importing torch), copied off the
        device once per version and behavior set, however many workers ask."""
        names = tuple(self._keys)
        if (
            self._published is None
            or self._published[0] != self.version
            or (tuple(self._published[1]) != names)
        ):
            current = {key: numpy_state(s.network) for key, s in self.behaviors.items()}
            states: Weights = {}
            for behavior, key in self._keys.items():
                states[behavior] = current[key]
                if self.behaviors[key].settings.self_play is not None:
                    brain, team = base_name(behavior), team_of(behavior)
                    states[behavior] = self.self_play.weights_of(brain, team, current[key])
            self._published = (self.version, states)
        return self._published

    # --- internals ----------------------------------------------------------------------

    def _behavior(self, behavior: str, spec: dict[str, Any]) -> BehaviorState:
        if behavior in self._keys:
            return self.behaviors[self._keys[behavior]]
        settings = self.config.for_behavior(behavior)
        key = behavior
        if settings.self_play is not None:  # the brain's first team holds its state
            brain = base_name(behavior)
            key = next((k for k in self.behaviors if base_name(k) == brain), behavior)
        if key not in self.behaviors:
            network = self.factory.network(key, spec_from_dict(spec))
            self.compute.place(network)
            self.behaviors[key] = BehaviorState(
                spec,
                settings,
                network,
                make_algorithm(network, settings, self.compute, self.experts),
                cloning=self._cloning(behavior, spec, settings, network),
            )
        self._keys[behavior] = key
        state = self.behaviors[key]
        if settings.self_play is not None:
            brain, team = base_name(behavior), team_of(behavior)
            self.self_play.join(brain, team, settings.self_play, numpy_state(state.network))
        return state

    def _cloning(
        self, behavior: str, spec: dict[str, Any], settings: TrainerSettings, network: ActorCritic
    ) -> BehavioralCloning | None:
        """The behavior's cloning from its demonstrations; a one-line error naming the
        file when they do not fit its spec."""
        if settings.behavioral_cloning is None:
            return None
        path = settings.behavioral_cloning.demo_path
        if (experts := self.experts.get(path)) is None:
            raise ValueError(f"behavioral_cloning of {base_name(behavior)}: {path} not loaded")
        if problem := experts.problem_with(spec_from_dict(spec)):
            raise ValueError(f"behavioral_cloning of {base_name(behavior)}: {problem}")
        h, device = settings.hyperparameters, self.compute.torch_device
        return BehavioralCloning(network, settings.behavioral_cloning, h, experts, device)

    def _update(self, behavior: str, state: BehaviorState) -> None:
        started = self._updating_since = time.perf_counter()
        try:  # schedules run over the config's max_steps; --max-steps only stops the run early
            report = state.algorithm.update(progress=state.steps / state.settings.max_steps)
            if state.cloning is not None:
                report |= state.cloning.update(state.steps)
        finally:
            self._updating_since = None
        self.stats.update_seconds += time.perf_counter() - started
        self.stats.samples += int(report.get("Policy/Samples", 0))
        self.stats.updates += 1
        self.version += 1
        state.updates.append(self.version)
        if state.settings.self_play is not None:
            report["Self-play/ELO"] = self.self_play.ghosts[base_name(behavior)].elo
        self._reports.append((behavior, state.steps, report))

    # --- for the driver -----------------------------------------------------------------

    def progress(self) -> dict[str, Any]:
        """Steps per behavior, whether all are done, learner throughput, and notes for the
        user (``Compute.note``: its process's log does not reach them under Ray)."""
        # copies: as a Ray actor (learner_actor) this runs while ``submit`` may
        steps = {name: s.steps for name, s in list(self.behaviors.items())}
        done = all_done(steps, self.config, self.max_steps)
        stats = replace(self.stats)
        if (since := self._updating_since) is not None:  # the update under way counts so far
            stats.update_seconds += time.perf_counter() - since
        notes = [self.compute.note] if self.compute.note else []
        return {
            "version": self.version,
            "steps": steps,
            "done": done,
            "stats": stats,
            "notes": notes,
        }

    def drain_reports(self) -> list[tuple[str, int, dict[str, float]]]:
        """(behavior, step, metrics) of each update since the last call (for TensorBoard)."""
        reports, self._reports = self._reports, []
        return reports

    def state_dict(self, behaviors: Collection[str] | None = None) -> dict[str, Any]:
        """Everything to resume (the layout of ``learners/host/checkpoint.py``), on the CPU: of
        every behavior, or of ``behaviors`` (each checkpoints on its own schedule)."""
        return to_cpu(
            {
                "step": sum(s.steps for s in self.behaviors.values()),
                "version": self.version,
                "behaviors": {
                    name: {
                        "spec": s.spec,
                        "trainer_type": s.settings.trainer_type,
                        "network_settings": checkpoint.network_settings_dict(s.network.settings),
                        "network": s.network.state_dict(),
                        "algorithm": s.algorithm.state_dict(),
                        "steps": s.steps,
                        "updates": list(s.updates),
                    }
                    for name, s in self.behaviors.items()
                    if behaviors is None or name in behaviors
                },
                "behavior_keys": dict(self._keys),
                "self_play": self.self_play.state_dict() if self.self_play.ghosts else None,
            }
        )

    def initialize(self, state: dict[str, Any]) -> None:
        """Start from another run's networks (``--initialize-from``): its weights and
        observation statistics, none of its steps, versions or optimizer state. They are a
        version of their own: workers start from the factory's weights, version 0, and take
        a newer version with their next collect (at 0 they would act with the factory's until the
        first update, and for ever with ``--inference``)."""
        self._published = None
        for name, entry in state["behaviors"].items():
            behavior = self._behavior(name, entry["spec"])
            behavior.network.load_state_dict(entry["network"])
            if behavior.settings.self_play is not None:
                self.self_play.start_from(base_name(name), numpy_state(behavior.network))
        self.version += 1

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.version = int(state["version"])
        self._published = None
        for name, entry in state["behaviors"].items():
            behavior = self._behavior(name, entry["spec"])
            behavior.network.load_state_dict(entry["network"])
            behavior.algorithm.load_state_dict(entry["algorithm"])
            behavior.steps = int(entry["steps"])
            behavior.updates = [int(v) for v in entry["updates"]]
        for behavior, key in state.get("behavior_keys", {}).items():
            if key in self.behaviors:
                self._keys[behavior] = key
        if state.get("self_play") is not None:
            brains = {base_name(key) for key in self.behaviors}
            settings = {b: self.config.for_behavior(b).self_play for b in brains}
            self.self_play.load_state_dict(state["self_play"], settings)


__all__ = ["Algorithm", "CentralLearner"]
