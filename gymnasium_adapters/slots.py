"""The Gymnasium side of one Unity behavior: its spaces, actions into ML-Agents'
``ActionTuple``, and :class:`BehaviorSlots`, which keeps each agent in a fixed slot across
ML-Agents' own resets (what ``gymnasium_adapters.env``'s environments step)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from mlagents_envs.base_env import ActionTuple, BehaviorSpec, DecisionSteps

from rollout.environment.unity import UnityError, UnityInstance

CONTINUOUS, DISCRETE = "continuous", "discrete"
DEFAULT_MAX_EXCHANGES = 1000


class AgentSetError(UnityError):
    """The behavior's agents came or went; the adapters need a fixed set."""


# --- spaces -------------------------------------------------------------------------------


def sensor_keys(spec: BehaviorSpec) -> list[str]:
    """Sensor names, made unique (``name_1``, ... for repeats), in the spec's order."""
    keys: list[str] = []
    for index, observation in enumerate(spec.observation_specs):
        keys.append(
            observation.name if observation.name not in keys else f"{observation.name}_{index}"
        )
    return keys


def observation_space(spec: BehaviorSpec) -> spaces.Space:
    """A ``Box`` per sensor (images: 3-D, in [0, 1]); a ``Dict`` by sensor name for several."""
    boxes = [
        spaces.Box(0.0, 1.0, o.shape, np.float32)
        if len(o.shape) == 3
        else spaces.Box(-np.inf, np.inf, o.shape, np.float32)
        for o in spec.observation_specs
    ]
    if len(boxes) == 1:
        return boxes[0]
    return spaces.Dict(dict(zip(sensor_keys(spec), boxes, strict=True)))


def action_space(spec: BehaviorSpec) -> spaces.Space:
    """``Box(-1, 1)``, ``Discrete(n)`` (one branch), ``MultiDiscrete``; hybrid: a ``Dict``."""
    actions = spec.action_spec
    parts: dict[str, spaces.Space] = {}
    if actions.continuous_size:
        parts[CONTINUOUS] = spaces.Box(-1.0, 1.0, (actions.continuous_size,), np.float32)
    branches = actions.discrete_branches
    if len(branches) == 1:
        parts[DISCRETE] = spaces.Discrete(int(branches[0]))
    elif branches:
        parts[DISCRETE] = spaces.MultiDiscrete([int(b) for b in branches])
    if not parts:
        raise UnityError("the behavior has no actions")
    return spaces.Dict(parts) if len(parts) == 2 else next(iter(parts.values()))


def _describe(space: spaces.Space) -> str:
    return repr(space).replace("\n", " ")


def to_action_tuple(
    action: Any, space: spaces.Space, spec: BehaviorSpec, agents: int, batched: bool
) -> ActionTuple:
    """The gym action (batched: leading dimension ``agents``) as an ML-Agents ActionTuple,
    or a one-line ``ValueError`` naming the expected shape (``space``: the unbatched one)."""
    if isinstance(space, spaces.Dict):
        if not isinstance(action, Mapping) or set(action) != {CONTINUOUS, DISCRETE}:
            raise ValueError(
                f"action must be a dict with keys 'continuous' and 'discrete' for "
                f"{_describe(space)}, got {type(action).__name__}"
            )
        parts = {key: action[key] for key in (CONTINUOUS, DISCRETE)}
        subspaces = {key: space[key] for key in (CONTINUOUS, DISCRETE)}
    else:
        key = DISCRETE if isinstance(space, spaces.Discrete | spaces.MultiDiscrete) else CONTINUOUS
        parts, subspaces = {key: action}, {key: space}
    continuous = np.zeros((agents, spec.action_spec.continuous_size), np.float32)
    discrete = np.zeros((agents, len(spec.action_spec.discrete_branches)), np.int32)
    for key, value in parts.items():
        sub = subspaces[key]
        expected = ((agents,) if batched else ()) + sub.shape
        array = np.asarray(value)
        if array.shape != expected:
            raise ValueError(
                f"action{'' if key == CONTINUOUS and len(parts) == 1 else f'[{key!r}]'} must have "
                f"shape {expected} for {_describe(sub)}"
                f"{f' x {agents} agents' if batched else ''}, got shape {array.shape}"
            )
        if key == CONTINUOUS:
            if not np.issubdtype(array.dtype, np.number):
                raise ValueError(f"continuous actions must be numbers, got dtype {array.dtype}")
            continuous = np.clip(array.reshape(agents, -1), -1.0, 1.0).astype(np.float32)
        else:
            if not np.issubdtype(array.dtype, np.integer) and not (
                np.issubdtype(array.dtype, np.floating) and np.all(array == np.round(array))
            ):
                raise ValueError(f"discrete actions must be integers, got dtype {array.dtype}")
            flat = array.reshape(agents, -1).astype(np.int64)
            limits = np.asarray(spec.action_spec.discrete_branches, np.int64)
            if (flat < 0).any() or (flat >= limits).any():
                raise ValueError(
                    f"discrete action out of range for branches {tuple(limits.tolist())}: "
                    f"{flat.tolist() if flat.size <= 16 else '...'}"
                )
            discrete = flat.astype(np.int32)
    return ActionTuple(continuous=continuous, discrete=discrete)


# --- the agents of one behavior, in fixed slots -----------------------------------------


@dataclasses.dataclass
class Outcome:
    """One gym step of all slots. ``obs``: per sensor, [n, ...] (the next episode's first
    observation where ``done``); ``final_obs``: the terminal observation where ``done``."""

    obs: list[np.ndarray]
    mask: np.ndarray | None  # [n, sum(branches)], True = allowed
    reward: np.ndarray  # float32 [n]
    terminated: np.ndarray  # bool [n]
    truncated: np.ndarray  # bool [n]
    final_obs: list[np.ndarray]

    @property
    def done(self) -> np.ndarray:
        return self.terminated | self.truncated


class BehaviorSlots:
    """Drives one behavior of a ``UnityInstance`` with its agents in fixed slots.

    The slot count is fixed at the first reset. An agent that ends its episode keeps its
    slot when it asks for a decision again (same id, or Basic's new id taking the freed
    slot) in the same decision round; anything else is an :class:`AgentSetError`.
    """

    def __init__(
        self, unity: UnityInstance, behavior: str, max_exchanges: int = DEFAULT_MAX_EXCHANGES
    ) -> None:
        self.unity = unity
        self.behavior = behavior
        self.spec = unity.behavior_specs[behavior]
        self.max_exchanges = max_exchanges
        self.slot_ids: np.ndarray = np.zeros(0, np.int64)
        self.num_agents: int | None = None
        self._order = np.zeros(0, np.int64)  # slot -> row of the current DecisionSteps
        self._mask_size = int(sum(self.spec.action_spec.discrete_branches))

    def reset(self, reset_unity: bool = True) -> tuple[list[np.ndarray], np.ndarray | None]:
        """Reset Unity (unless just done); the agents' first observations and masks."""
        if reset_unity:
            self.unity.reset()
        for _ in range(self.max_exchanges):
            decisions, _ = self.unity.get_steps(self.behavior)
            if len(decisions):
                break
            self.unity.step()  # nobody waits for an action: nothing to set
        else:
            raise UnityError(f"{self.behavior}: no agent asked for a decision after reset")
        if self.num_agents is None:
            self.num_agents = len(decisions)
        elif len(decisions) != self.num_agents:
            raise AgentSetError(
                f"{self.behavior}: {len(decisions)} agents after reset, {self.num_agents} before; "
                f"the adapters need a fixed set of agents"
            )
        self.slot_ids = decisions.agent_id.astype(np.int64)
        self._order = np.arange(len(decisions))
        return [o.copy() for o in decisions.obs], self._mask(decisions)

    def step(self, actions: ActionTuple, last_obs: Sequence[np.ndarray]) -> Outcome:
        """Send one action per slot; exchange until the agents decide again."""
        n = len(self.slot_ids)
        inverse = np.empty(n, np.int64)
        inverse[self._order] = np.arange(n)  # row of DecisionSteps -> slot
        self.unity.set_actions(
            self.behavior,
            ActionTuple(continuous=actions.continuous[inverse], discrete=actions.discrete[inverse]),
        )
        reward = np.zeros(n, np.float32)
        terminated = np.zeros(n, np.bool_)
        truncated = np.zeros(n, np.bool_)
        final_obs = [o.copy() for o in last_obs]
        for _ in range(self.max_exchanges):
            self.unity.step()
            decisions, terminals = self.unity.get_steps(self.behavior)
            if len(terminals):
                slots = self._slots_of(terminals.agent_id)
                reward[slots] += terminals.reward
                truncated[slots] = terminals.interrupted
                terminated[slots] = ~terminals.interrupted
                for final, observation in zip(final_obs, terminals.obs, strict=True):
                    final[slots] = observation
            if not len(decisions):
                continue
            self._assign(decisions, terminated | truncated)
            live = ~(terminated | truncated)  # a new episode's first reward is not ours
            reward[live] += decisions.reward[self._order][live]
            obs = [o[self._order] for o in decisions.obs]
            return Outcome(obs, self._mask(decisions), reward, terminated, truncated, final_obs)
        raise UnityError(
            f"{self.behavior}: no decision in {self.max_exchanges} exchanges with Unity"
        )

    def _mask(self, decisions: DecisionSteps) -> np.ndarray | None:
        if not self._mask_size:
            return None
        if decisions.action_mask is None:
            return np.ones((len(self._order), self._mask_size), np.bool_)
        return ~np.concatenate(decisions.action_mask, axis=1)[self._order]

    def _slots_of(self, agent_ids: np.ndarray) -> np.ndarray:
        where = {int(a): i for i, a in enumerate(self.slot_ids)}
        unknown = [int(a) for a in agent_ids if int(a) not in where]
        if unknown:
            raise AgentSetError(
                f"{self.behavior}: agent(s) {unknown} ended an episode without having acted; "
                "the adapters need a fixed set of agents (use rollout.collecting.collector for "
                "this one)"
            )
        return np.asarray([where[int(a)] for a in agent_ids], np.int64)

    def _assign(self, decisions: DecisionSteps, done: np.ndarray) -> None:
        """Map the decision rows onto the slots; a finished agent's slot may take a new id."""
        index = decisions.agent_id_to_index
        order = np.asarray([index.get(int(a), -1) for a in self.slot_ids], np.int64)
        newcomers = sorted(set(range(len(decisions))) - set(order.tolist()))
        free = np.flatnonzero((order < 0) & done)
        for slot, row in zip(free, newcomers, strict=False):
            order[slot] = row
            self.slot_ids[slot] = int(decisions.agent_id[row])
        if (order < 0).any() or len(newcomers) > len(free):
            gone = [int(self.slot_ids[s]) for s in np.flatnonzero(order < 0)]
            extra = [int(decisions.agent_id[r]) for r in newcomers[len(free) :]]
            raise AgentSetError(
                f"{self.behavior}: the agent set changed (missing {gone}, new {extra}, "
                f"{len(decisions)} deciding of {len(self.slot_ids)}); the adapters need a fixed "
                "set of agents deciding together (use rollout.collecting.collector for this "
                "behavior)"
            )
        self._order = order


# --- construction helpers -----------------------------------------------------------------
