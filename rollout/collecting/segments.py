"""Trajectory assembly for one behavior: per-agent transitions into packed trajectories.

Unity reports, per exchange, the agents that need a decision and those whose episode ended
(the same agent may be in both; agents appear, disappear and move between behaviors). A
transition is (observation, action) at a decision, completed by the agent's *next* info:
a terminal one (``done``; ``terminated`` unless interrupted, else ``truncated``) or a
decision one (not done). Each agent fills a row until its episode ends or the row holds
``horizon`` transitions (ML-Agents' ``time_horizon``), whichever comes first, exactly when
ML-Agents' agent processor hands a trajectory to its trainer; a row cut at the horizon
gets ``truncated`` (and ``done``) on its last step, so the learner bootstraps there.
Finished rows leave packed: one ``[N]`` :class:`Segment`, each row's steps contiguous and
in order, no padding. An agent silent for ``STALE_FACTOR * gone_after`` exchanges without a
terminal info has its row cut the same way; an ended agent that does not come back within
``gone_after`` exchanges gives its slot up.

Everything is vectorized over the agents of the exchange: numpy fancy indexing into
per-slot buffers, never a Python loop over agents.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mlagents_envs.base_env import BehaviorSpec, DecisionSteps, TerminalSteps

from batches import keys, specs
from batches.segment import Segment
from rollout.collecting.decisions import Decisions, allowed_mask
from rollout.collecting.episode_ends import EpisodeEnds, EpisodeLog
from rollout.collecting.groups import Groupmates

INITIAL_SLOTS = 16
STALE_FACTOR = 10  # an agent silent for STALE_FACTOR * gone_after exchanges is cut off
GONE_AFTER = 64  # at least: exchanges an ended agent may stay away before its slot is freed


@dataclass
class Counters:
    steps: int = 0  # transitions recorded
    rows: int = 0  # rows emitted
    dropped_steps: int = 0  # transitions thrown away (e.g. the player crashed mid-row)
    emitted_steps: int = 0  # transitions handed out in rows
    lost_steps: int = 0  # recorded transitions in rows thrown away (player failure)
    reset_steps: int = 0  # recorded transitions in rows thrown away (a lesson's reset)
    unmatched_terminals: int = 0  # terminal infos of agents that never acted


class SegmentBuilder:
    """Builds packed :class:`Segment` s for one behavior.

    Per exchange: ``observe(decisions, terminals)``, then ``collect()`` for finished rows,
    then (a recurrent policy) ``memories(decisions)`` for what it reads, then
    ``act(decisions, chosen, policy_version)`` with the policy's choices. Row storage
    is ``(slots, horizon)`` per field, so the horizon bounds memory per agent.

    A recurrent policy's memory after an agent's last decision lives in the agent's slot
    (``carry``): kept across the agent's decision gaps, zeros at an episode's start, gone
    with the slot (a freed agent, a Unity restart, a lesson reset), as ML-Agents' policy
    keeps its memories by agent id.
    """

    def __init__(
        self,
        behavior: str,
        spec: BehaviorSpec,
        horizon: int,
        worker: int = 0,
        gone_after: int | None = None,
        pixel_sensors: frozenset[str] = frozenset(),
        memory_size: int = 0,
    ) -> None:
        """``pixel_sensors``: sensors whose values are k/255 (Unity sent them as PNG), kept
        as uint8 0..255 from here to the learner: a quarter of float32's bytes.
        ``memory_size``: a recurrent policy's, whose memory each step keeps (``MEMORY``)."""
        self.behavior = behavior
        self.spec = spec
        self.horizon = horizon
        self.worker = worker
        self._memory = memory_size
        self._spec_dict = specs.spec_to_dict(spec)  # travels with each segment to the learner
        self.gone_after = gone_after or max(horizon, GONE_AFTER)
        self.counters = Counters()
        self.episodes = EpisodeLog()  # for the metrics
        self._sensors = [(o.name, o.shape) for o in spec.observation_specs]
        self._pixels = frozenset(pixel_sensors)
        self._continuous = spec.action_spec.continuous_size
        self._branches = len(spec.action_spec.discrete_branches)
        self._mask_size = int(sum(spec.action_spec.discrete_branches))
        stored = [(n, s, np.uint8 if n in self._pixels else np.float32) for n, s in self._sensors]
        self.groups = Groupmates(stored, self._continuous, self._branches, 0, horizon)
        self._allocate(INITIAL_SLOTS)

    # --- storage ------------------------------------------------------------------------

    def _fields(self, slots: int) -> dict[str, np.ndarray]:
        """Per-slot storage: row buffers ``(S, T, ...)`` and pending decisions ``(S, ...)``."""
        s, t = slots, self.horizon
        fields = {
            "cont": np.zeros((s, t, self._continuous), np.float32),
            "disc": np.zeros((s, t, self._branches), np.int64),
            "mask": np.ones((s, t, self._mask_size), np.bool_),
            "logp": np.zeros((s, t, self._continuous + self._branches), np.float32),
            "memory": np.zeros((s, t, self._memory), np.float32),  # 0 wide without memory
            "version": np.zeros((s, t), np.int64),
            "group": np.zeros((s, t), np.int64),
            "reward": np.zeros((s, t), np.float32),
            "group_reward": np.zeros((s, t), np.float32),
            "done": np.zeros((s, t), np.bool_),
            "terminated": np.zeros((s, t), np.bool_),
            "truncated": np.zeros((s, t), np.bool_),
            "p_cont": np.zeros((s, self._continuous), np.float32),
            "p_disc": np.zeros((s, self._branches), np.int64),
            "p_mask": np.ones((s, self._mask_size), np.bool_),
            "p_logp": np.zeros((s, self._continuous + self._branches), np.float32),
            "p_memory": np.zeros((s, self._memory), np.float32),
            "carry": np.zeros((s, self._memory), np.float32),  # the memory its next decision reads
            "p_version": np.zeros(s, np.int64),
            "p_group": np.zeros(s, np.int64),
            "length": np.zeros(s, np.int64),
            "pending": np.zeros(s, np.bool_),
            "ended": np.zeros(s, np.bool_),
            "idle": np.zeros(s, np.int64),
            "ep_return": np.zeros(s, np.float64),
            "ep_group": np.zeros(s, np.float64),
            "ep_mates": np.zeros(s, np.float64),
            "ep_length": np.zeros(s, np.int64),
            "agent": np.full(s, -1, np.int64),  # agent id per slot, -1 = free
        }
        for name, shape in self._sensors:
            dtype = np.uint8 if name in self._pixels else np.float32
            fields[f"obs/{name}"] = np.zeros((s, t, *shape), dtype)
            fields[f"next/{name}"] = np.zeros((s, t, *shape), dtype)
            fields[f"p_obs/{name}"] = np.zeros((s, *shape), dtype)
        return fields

    def _allocate(self, slots: int) -> None:
        old = getattr(self, "_f", None)
        self._f = self._fields(slots)
        if old is not None:
            for name, array in old.items():
                self._f[name][: len(array)] = array
        self.groups.resize(slots)

    def _slots(self, ids: np.ndarray, create: bool) -> np.ndarray:
        """Slot of each agent id (vectorized); -1 for unknown ids unless ``create``."""
        agent = self._f["agent"]
        active = np.flatnonzero(agent >= 0)
        slots = np.full(len(ids), -1, np.int64)
        if len(active):
            order = np.argsort(agent[active])
            sorted_ids = agent[active][order]
            pos = np.minimum(np.searchsorted(sorted_ids, ids), len(sorted_ids) - 1)
            found = sorted_ids[pos] == ids
            slots[found] = active[order][pos[found]]
        new = np.flatnonzero(slots < 0)
        if create and len(new):
            free = np.flatnonzero(agent < 0)
            if len(free) < len(new):
                self._allocate(max(2 * len(agent), len(agent) + len(new)))
                free = np.flatnonzero(self._f["agent"] < 0)
            chosen = free[: len(new)]
            f = self._f
            f["agent"][chosen] = ids[new]
            fresh = ("length", "idle", "ep_return", "ep_length", "ep_group", "ep_mates", "carry")
            for name in fresh:
                f[name][chosen] = 0
            for name in ("pending", "ended"):
                f[name][chosen] = False
            self.groups.forget(chosen)
            slots[new] = chosen
        return slots

    # --- one exchange -------------------------------------------------------------------

    def observe(self, decisions: DecisionSteps, terminals: TerminalSteps) -> None:
        """Complete the pending transitions of agents that reported in this exchange."""
        f = self._f
        f["idle"][f["agent"] >= 0] += 1
        slots_ended = np.zeros(0, np.int64)
        if len(terminals):
            slots = slots_ended = self._slots(terminals.agent_id.astype(np.int64), create=False)
            known = slots >= 0
            f["ended"][slots[known]] = True
            f["carry"][slots[known]] = 0.0  # the next episode starts from zeros
            f["idle"][slots[known]] = 0
            rows = np.flatnonzero(known & f["pending"][np.maximum(slots, 0)])
            self.counters.unmatched_terminals += len(terminals) - len(rows)
            self._complete(
                slots[rows],
                [o[rows] for o in terminals.obs],
                terminals.reward[rows],
                terminals.group_reward[rows],
                np.asarray(terminals.group_id, np.int64)[rows],
                done=np.ones(len(rows), np.bool_),
                truncated=terminals.interrupted[rows],
            )
        if len(decisions):
            slots = self._slots(decisions.agent_id.astype(np.int64), create=True)
            f = self._f  # the storage may have grown for new agents
            f["ended"][slots] = False
            f["idle"][slots] = 0
            rows = np.flatnonzero(f["pending"][slots])
            none = np.zeros(len(rows), np.bool_)
            self._complete(
                slots[rows],
                [o[rows] for o in decisions.obs],
                decisions.reward[rows],
                decisions.group_reward[rows],
                np.asarray(decisions.group_id, np.int64)[rows],
                done=none,
                truncated=none,
            )
        if len(terminals):  # ended agents leave their groups' statuses after the exchange
            self.groups.forget(slots_ended[slots_ended >= 0])

    def _complete(
        self,
        slots: np.ndarray,
        next_obs: list[np.ndarray],
        reward: np.ndarray,
        group_reward: np.ndarray,
        group: np.ndarray,
        done: np.ndarray,
        truncated: np.ndarray,
    ) -> None:
        """Complete pending transitions; first, as ML-Agents, the reporting agents' group
        statuses, then each transition's groupmates (``rollout.collecting.groups``)."""
        if not len(slots):
            return
        f = self._f
        t = f["length"][slots]
        acted = [f[f"p_obs/{name}"][slots] for name, _ in self._sensors]
        now = [self._stored(name, v) for (name, _), v in zip(self._sensors, next_obs, strict=True)]
        mates_play_on, mates_reward = np.zeros(len(slots), np.bool_), 0.0
        if self.groups.capacity or (group > 0).any():  # none of it for behaviors sans groups
            self.groups.set_status(
                slots, group, acted, f["p_cont"][slots], f["p_disc"][slots], now, reward, done
            )
            mates_play_on, mates_reward = self.groups.record(slots, t, group)
        for (name, _), before, after in zip(self._sensors, acted, now, strict=True):
            f[f"obs/{name}"][slots, t] = before
            f[f"next/{name}"][slots, t] = after
        for row in ("cont", "disc", "mask", "logp", "memory", "version", "group"):
            f[row][slots, t] = f[f"p_{row}"][slots]
        f["reward"][slots, t] = reward
        f["group_reward"][slots, t] = group_reward
        f["done"][slots, t] = done
        f["terminated"][slots, t] = done & ~truncated
        f["truncated"][slots, t] = truncated
        f["length"][slots] += 1
        f["pending"][slots] = False
        self.counters.steps += len(slots)
        f["ep_return"][slots] += reward
        f["ep_length"][slots] += 1
        f["ep_group"][slots] += group_reward
        f["ep_mates"][slots] += mates_reward
        ended = slots[done]
        if len(ended):
            columns = ("ep_return", "ep_length", "ep_group", "ep_mates")
            with_group = ((group > 0) & ~mates_play_on)[done]
            self.episodes.add(EpisodeEnds(*(f[name][ended] for name in columns)), with_group)
            f["ep_return"][ended] = f["ep_group"][ended] = f["ep_mates"][ended] = 0.0
            f["ep_length"][ended] = 0

    def _stored(self, name: str, values: np.ndarray) -> np.ndarray:
        """A pixel sensor's floats k/255 as the uint8 k (exact); other sensors as they are."""
        if name not in self._pixels:
            return values
        return np.rint(values * np.float32(255.0)).astype(np.uint8)

    def memories(self, decisions: DecisionSteps) -> np.ndarray:
        """``[n, memory_size]``: what each decision agent's recurrent policy reads."""
        return self._f["carry"][self._slots(decisions.agent_id.astype(np.int64), create=True)]

    def act(self, decisions: DecisionSteps, chosen: Decisions, policy_version: int) -> None:
        """Remember what the decision agents were told to do, to complete next exchange."""
        if not len(decisions):
            return
        slots = self._slots(decisions.agent_id.astype(np.int64), create=True)
        f = self._f  # read after _slots: the storage may have grown
        for (name, _), values in zip(self._sensors, decisions.obs, strict=True):
            f[f"p_obs/{name}"][slots] = self._stored(name, values)
        f["p_cont"][slots] = chosen.continuous
        f["p_disc"][slots] = chosen.discrete
        f["p_logp"][slots] = chosen.log_prob
        if self._memory and chosen.after is not None:
            f["p_memory"][slots] = f["carry"][slots]  # what the decision read (``memories``)
            f["carry"][slots] = chosen.after
        f["p_version"][slots] = policy_version
        f["p_group"][slots] = decisions.group_id
        if self._mask_size:
            f["p_mask"][slots] = allowed_mask(decisions, self._mask_size)
        f["pending"][slots] = True

    def collect(self, env_steps: int = 0) -> Segment | None:
        """Finished rows as one packed ``[N]`` segment, or None when none finished."""
        f = self._f
        active = f["agent"] >= 0
        length = f["length"]
        last = np.maximum(length - 1, 0)
        ended_row = active & (length > 0) & f["done"][np.arange(len(length)), last]
        full = active & (length == self.horizon)
        silent = active & ~f["ended"] & (f["idle"] > STALE_FACTOR * self.gone_after)
        if silent.any():  # vanished without a terminal info: its pending step is lost
            self.counters.dropped_steps += int(f["pending"][silent].sum())
        rows = np.flatnonzero(ended_row | full | (silent & (length > 0)))
        batch = self._rows(rows, env_steps) if len(rows) else None
        length[rows] = 0
        gone = active & f["ended"] & (f["idle"] > self.gone_after)
        f["agent"][gone | silent] = -1
        self.groups.forget(np.flatnonzero(gone | silent))
        return batch

    def _rows(self, slots: np.ndarray, env_steps: int) -> Segment:
        f = self._f
        lengths = f["length"][slots]
        n = int(lengths.sum())
        row_of = np.repeat(slots, lengths)  # per packed step: its slot and its time index
        starts = np.cumsum(lengths) - lengths
        time = np.arange(n) - np.repeat(starts, lengths)
        ends = starts + lengths - 1
        # A row that stops short of an episode end is a cut: bootstrap from its last step.
        done = f["done"][row_of, time]
        truncated = f["truncated"][row_of, time]
        cut = ends[~done[ends]]
        done[cut], truncated[cut] = True, True
        cuts = np.zeros(n, np.bool_)
        cuts[cut] = True

        def take(name: str, scalar: bool = False) -> np.ndarray:
            array = f[name][row_of, time]
            return array[:, None] if scalar else array

        def flag(values: np.ndarray) -> np.ndarray:
            return values[:, None]

        action = {}
        if self._continuous:
            action[keys.CONTINUOUS] = take("cont")
        if self._branches:
            action[keys.DISCRETE] = take("disc")
        data = {
            keys.OBS: {name: take(f"obs/{name}") for name, _ in self._sensors},
            keys.ACTION: action,
            keys.LOG_PROB: take("logp"),
            keys.POLICY_VERSION: take("version"),
            keys.GROUP_ID: take("group"),
            keys.AGENT_ID: f["agent"][row_of],
            keys.WORKER: np.full(n, self.worker, np.int64),
            keys.ENV_STEPS: np.full(n, env_steps, np.int64),
            keys.NEXT: {
                keys.OBS: {name: take(f"next/{name}") for name, _ in self._sensors},
                keys.REWARD: take("reward", scalar=True),
                keys.GROUP_REWARD: take("group_reward", scalar=True),
                keys.DONE: flag(done),
                keys.TERMINATED: take("terminated", scalar=True),
                keys.TRUNCATED: flag(truncated),
                keys.CUT: flag(cuts),
            },
        }
        if self._mask_size:
            data[keys.ACTION_MASK] = take("mask")
        if self._memory:
            data[keys.MEMORY] = take("memory")
        data[keys.GROUPMATES], data[keys.NEXT][keys.GROUPMATES] = self.groups.take(row_of, time)
        self.counters.rows += len(slots)
        self.counters.emitted_steps += n
        return Segment(self.behavior, self._spec_dict, data)

    def in_progress(self) -> int:
        """Recorded transitions in rows not handed out yet: ``steps == emitted_steps + lost_steps +
        reset_steps + in_progress()`` (the sample ledger, ``rollout.collecting.ledger``)."""
        return int(self._f["length"][self._f["agent"] >= 0].sum())

    def drop_partial(self, lesson_reset: bool = False) -> int:
        """Forget every unfinished row (the player died, or a lesson reset Unity): returns
        the steps dropped."""
        f = self._f
        active = f["agent"] >= 0
        lost = int(f["length"][active].sum())
        if lesson_reset:
            self.counters.reset_steps += lost
        else:
            self.counters.lost_steps += lost
        dropped = lost + int(f["pending"][active].sum())
        f["agent"][:], f["length"][:], f["pending"][:] = -1, 0, False
        self.groups.forget(np.arange(len(f["agent"])))
        self.counters.dropped_steps += dropped
        return dropped
