"""Gymnasium adapters over one Unity behavior, for users of other RL libraries.

``UnityGymEnv`` is a ``gymnasium.Env`` for a behavior with exactly one agent (Basic);
``UnityVectorEnv`` is a ``gymnasium.vector.VectorEnv`` over all agents of one behavior
(3DBall: 12), each agent a sub-environment, in autoreset mode SAME_STEP: ML-Agents resets
an agent on its own, so the step that ends its episode already returns the new episode's
first observation, and the final one goes to ``info["final_obs"]``. Both own a
:class:`rollout.environment.unity.UnityInstance` (leased port, restarts) and end it in ``close()``.

Observations: one ``Box`` per sensor (float32; 3-D sensors are images [C, H, W] in
[0, 1]), a ``Dict`` keyed by sensor name for several. Actions: ``Box(-1, 1)``,
``Discrete``, ``MultiDiscrete``, or for hybrid specs a ``Dict`` with keys "continuous" and
"discrete". Masks: ``info["action_mask"]``, flat over the branches, True = allowed.
ML-Agents' ``interrupted`` is ``truncated``. Seeded resets restart the player with the seed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from mlagents_envs.base_env import ActionTuple

from gymnasium_adapters.slots import (
    DEFAULT_MAX_EXCHANGES,
    AgentSetError,
    BehaviorSlots,
    Outcome,
    action_space,
    observation_space,
    sensor_keys,
    to_action_tuple,
)
from rollout.environment.ports import PortAllocator, PortRange
from rollout.environment.unity import RECOVERABLE, UnityConfig, UnityError, UnityInstance


def _config(build: str | UnityConfig | None, seed: int | None, **overrides: Any) -> UnityConfig:
    config = build if isinstance(build, UnityConfig) else UnityConfig(build)
    if seed is not None:
        overrides["seed"] = int(seed)
    return dataclasses.replace(config, **{k: v for k, v in overrides.items() if v is not None})


def _allocator(
    allocator: PortAllocator | None, port_range: PortRange | str | None
) -> PortAllocator:
    if allocator is not None:
        return allocator
    if isinstance(port_range, str):
        port_range = PortRange.parse(port_range)
    return PortAllocator(port_range)


def _pick_behavior(unity: UnityInstance, behavior: str | None) -> str:
    names = list(unity.behavior_specs)
    if behavior is None:
        if len(names) != 1:
            raise UnityError(
                f"{unity.config.build} has {len(names)} behaviors {names}: pass behavior=<name>"
            )
        return names[0]
    if behavior not in names:
        raise UnityError(f"{unity.config.build} has no behavior {behavior!r}; it has {names}")
    return behavior


class _Owner:
    """The Unity instance and slots both adapters own; seeded resets restart the player."""

    def __init__(
        self,
        config: UnityConfig,
        behavior: str | None,
        allocator: PortAllocator,
        max_exchanges: int,
    ) -> None:
        self.config = config
        self.allocator = allocator
        self.max_exchanges = max_exchanges
        self.unity = UnityInstance(config, allocator)
        self.unity.start()
        try:
            self.unity.reset()  # Unity sends the behavior specs with the first reset
            self.behavior = _pick_behavior(self.unity, behavior)
            self.slots = BehaviorSlots(self.unity, self.behavior, max_exchanges)
            self.spec = self.slots.spec
            self.first = self.slots.reset(reset_unity=False)
        except BaseException:
            self.unity.close()
            raise
        self.pristine = True  # nothing sent since the player started with config.seed
        self.restarted = False  # the last step restarted a failed player

    def restart(self, seed: int) -> tuple[list[np.ndarray], np.ndarray | None]:
        """A fresh player seeded ``seed`` (unless the running one is untouched and is)."""
        if self.pristine and seed == self.config.seed:
            self.pristine = False
            return self.first
        self.unity.close()
        self.config = dataclasses.replace(self.config, seed=seed)
        self.unity = UnityInstance(self.config, self.allocator)
        self.unity.start()
        self.slots.unity = self.unity
        self.pristine = False
        return self.slots.reset()

    def reset(self) -> tuple[list[np.ndarray], np.ndarray | None]:
        if self.pristine:
            self.pristine = False
            return self.first
        return self.slots.reset()

    def step(self, actions: ActionTuple, last_obs: Sequence[np.ndarray]) -> Outcome:
        """One gym step; if the player fails, it restarts (within the config's budget) and
        every episode ends truncated at its last observation, with ``restarted`` set."""
        self.restarted = False
        try:
            outcome = self.slots.step(actions, last_obs)
        except UnityError:
            raise
        except RECOVERABLE as error:
            self.unity.restart(f"{type(error).__name__}: {error}")
            obs, mask = self.slots.reset()
            n = len(self.slots.slot_ids)
            self.restarted = True
            return Outcome(
                obs,
                mask,
                np.zeros(n, np.float32),
                np.zeros(n, np.bool_),
                np.ones(n, np.bool_),
                [o.copy() for o in last_obs],
            )
        self.unity.healthy_step()
        return outcome

    def close(self) -> None:
        self.unity.close()


class _HoldsOwner:
    """What both adapters share: the owner of the Unity instance, until closed."""

    _owner: _Owner | None = None

    @property
    def unity(self) -> UnityInstance:
        return self._require().unity

    def _require(self) -> _Owner:
        if self._owner is None:
            raise UnityError("the environment is closed")
        return self._owner

    def _close_owner(self) -> None:
        owner, self._owner = self._owner, None
        if owner is not None:
            owner.close()


def _as_obs(arrays: Sequence[np.ndarray], keys: list[str]) -> Any:
    return arrays[0] if len(arrays) == 1 else dict(zip(keys, arrays, strict=True))


# --- the single-agent environment ---------------------------------------------------------


class UnityGymEnv(_HoldsOwner, gym.Env):
    """One single-agent Unity behavior as a ``gymnasium.Env``.

    ``build``: ``"unitysim:Basic"``, a build path, None (the editor) or a ``UnityConfig``;
    ``seed`` overrides the config's. ``info["action_mask"]`` (discrete branches only) and
    ``action_masks()`` give the allowed actions; ``info["episode"]`` = {"r", "l"} at the end.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        build: str | UnityConfig | None,
        behavior: str | None = None,
        seed: int | None = None,
        *,
        allocator: PortAllocator | None = None,
        port_range: PortRange | str | None = None,
        max_exchanges: int = DEFAULT_MAX_EXCHANGES,
    ) -> None:
        self._owner: _Owner | None = None
        config = _config(build, seed)
        owner = _Owner(config, behavior, _allocator(allocator, port_range), max_exchanges)
        if len(owner.slots.slot_ids) != 1:
            owner.close()
            raise UnityError(
                f"{owner.behavior} has {len(owner.slots.slot_ids)} agents; UnityGymEnv needs "
                f"exactly one: use UnityVectorEnv"
            )
        self._owner = owner
        self.behavior_name = owner.behavior
        self.behavior_spec = owner.spec
        self._keys = sensor_keys(owner.spec)
        self.observation_space = observation_space(owner.spec)
        self.action_space = action_space(owner.spec)
        self._obs: list[np.ndarray] = []
        self._mask: np.ndarray | None = None
        self._next: tuple[list[np.ndarray], np.ndarray | None] | None = None
        self._return, self._length = 0.0, 0

    def _info(self) -> dict[str, Any]:
        info: dict[str, Any] = {"agent_id": int(self._require().slots.slot_ids[0])}
        if self._mask is not None:
            info["action_mask"] = self._mask[0].copy()
        return info

    def action_masks(self) -> np.ndarray:
        """Allowed actions, flat over the branches (for sb3-contrib's MaskablePPO)."""
        if self._mask is None:
            return np.ones(int(sum(self.behavior_spec.action_spec.discrete_branches)), np.bool_)
        return self._mask[0].copy()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """A new episode. With ``seed`` the player restarts with it; without, a finished
        episode continues with the agent's next one (Unity already reset it)."""
        super().reset(seed=seed)
        owner = self._require()
        if seed is not None:
            self._obs, self._mask = owner.restart(seed)
        elif self._next is not None:  # the agent's next episode has begun already
            self._obs, self._mask = self._next
        elif not self._obs or self._length:  # the first reset, or one mid-episode
            self._obs, self._mask = owner.reset()
        self._next = None
        self._return, self._length = 0.0, 0
        return _as_obs([o[0].copy() for o in self._obs], self._keys), self._info()

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        owner = self._require()
        if not self._obs:
            raise UnityError("call reset() before step()")
        if self._next is not None:
            raise UnityError("the episode has ended: call reset() before step()")
        actions = to_action_tuple(action, self.action_space, owner.spec, 1, batched=False)
        outcome = owner.step(actions, self._obs)
        reward = float(outcome.reward[0])
        terminated, truncated = bool(outcome.terminated[0]), bool(outcome.truncated[0])
        self._return += reward
        self._length += 1
        if terminated or truncated:
            obs = [o[0].copy() for o in outcome.final_obs]
            self._next = (outcome.obs, outcome.mask)
            info: dict[str, Any] = {"episode": {"r": self._return, "l": self._length}}
            if owner.restarted:
                info["unity_restarted"] = True
            return _as_obs(obs, self._keys), reward, terminated, truncated, info
        self._obs, self._mask = outcome.obs, outcome.mask
        obs = [o[0].copy() for o in outcome.obs]
        return _as_obs(obs, self._keys), reward, False, False, self._info()

    def close(self) -> None:
        self._close_owner()


# --- all agents of a behavior as a vector environment -------------------------------------


class UnityVectorEnv(_HoldsOwner, VectorEnv):
    """All agents of one behavior as a ``gymnasium.vector.VectorEnv`` (SAME_STEP autoreset).

    ``num_envs`` is the agent count at the first reset. When agent ``i`` ends an episode,
    ``step`` returns its next episode's first observation, ``terminated``/``truncated``,
    and ``info["final_obs"][i]`` (``info["_final_obs"]`` marks which) and
    ``info["episode"]`` = {"r", "l"} (``info["_episode"]``). ``info["action_mask"]``
    [num_envs, sum(branches)] for discrete branches. Agents that come and go raise
    :class:`AgentSetError`.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        build: str | UnityConfig | None,
        behavior: str | None = None,
        seed: int | None = None,
        *,
        num_areas: int | None = None,
        allocator: PortAllocator | None = None,
        port_range: PortRange | str | None = None,
        max_exchanges: int = DEFAULT_MAX_EXCHANGES,
    ) -> None:
        self._owner: _Owner | None = None
        config = _config(build, seed, num_areas=num_areas)
        owner = _Owner(config, behavior, _allocator(allocator, port_range), max_exchanges)
        self._owner = owner
        self.behavior_name = owner.behavior
        self.behavior_spec = owner.spec
        self.num_envs = len(owner.slots.slot_ids)
        self._keys = sensor_keys(owner.spec)
        self.single_observation_space = observation_space(owner.spec)
        self.single_action_space = action_space(owner.spec)
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, self.num_envs
        )
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self._obs: list[np.ndarray] = []
        self._mask: np.ndarray | None = None
        self._returns = np.zeros(self.num_envs, np.float64)
        self._lengths = np.zeros(self.num_envs, np.int64)

    def _info(self) -> dict[str, Any]:
        info: dict[str, Any] = {"agent_id": self._require().slots.slot_ids.copy()}
        if self._mask is not None:
            info["action_mask"] = self._mask.copy()
            info["_action_mask"] = np.ones(self.num_envs, np.bool_)
        return info

    def reset(
        self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every agent (a Unity reset); ``seed`` restarts the player with it."""
        if isinstance(seed, list | tuple):
            if len(set(seed)) > 1:
                raise ValueError("UnityVectorEnv takes one seed for all agents (one Unity player)")
            seed = seed[0] if seed else None
        super().reset(seed=seed)
        owner = self._require()
        self._obs, self._mask = owner.restart(seed) if seed is not None else owner.reset()
        self._returns[:] = 0.0
        self._lengths[:] = 0
        return _as_obs([o.copy() for o in self._obs], self._keys), self._info()

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        owner = self._require()
        if not self._obs:
            raise UnityError("call reset() before step()")
        action_tuple = to_action_tuple(
            actions, self.single_action_space, owner.spec, self.num_envs, batched=True
        )
        outcome = owner.step(action_tuple, self._obs)
        self._obs, self._mask = outcome.obs, outcome.mask
        self._returns += outcome.reward
        self._lengths += 1
        info = self._info()
        if owner.restarted:
            info["unity_restarted"] = True
        done = outcome.done
        if done.any():
            final = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(done):
                final[i] = _as_obs([o[i].copy() for o in outcome.final_obs], self._keys)
            info["final_obs"], info["_final_obs"] = final, done.copy()
            info["episode"] = {
                "r": np.where(done, self._returns, 0.0),
                "l": np.where(done, self._lengths, 0),
                "_r": done.copy(),
                "_l": done.copy(),
            }
            info["_episode"] = done.copy()
            self._returns[done] = 0.0
            self._lengths[done] = 0
        obs = _as_obs([o.copy() for o in outcome.obs], self._keys)
        return obs, outcome.reward.copy(), outcome.terminated, outcome.truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        self._close_owner()

    def __enter__(self) -> UnityVectorEnv:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


__all__ = ["AgentSetError", "UnityGymEnv", "UnityVectorEnv"]
