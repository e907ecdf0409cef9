"""A PettingZoo ``ParallelEnv`` over every agent of every behavior of one Unity build.

ML-Agents' own PettingZoo wrapper (``mlagents_envs.envs``) targets gym and PettingZoo
1.15's API (``step`` returns four dicts, ``reset`` no infos); this one follows the current
API. Unity's agents come and go (DungeonEscape's sacrificed knight, WallJump's agents
changing behavior), and an agent that ends its episode starts the next one by itself with
the same id. PettingZoo's agents never come back once done, so each agent is named per
episode: ``"<behavior>?agent_id=<id>"`` for its first, ``...&episode=<n>`` after. An
agent is in ``agents`` from its first decision until its episode ends (terminated, or
truncated where ML-Agents says interrupted); ``possible_agents`` holds every name seen.

``step(actions)`` sends each deciding agent's action and exchanges with Unity until some
agent decides or ends again. Observations and spaces are the Gymnasium adapters' (a
``Box`` per sensor, a ``Dict`` by sensor name for several); ``infos[agent]`` carries
``behavior``, ``group_id``, ``group_reward`` and, for discrete actions, ``action_mask``
(True = allowed). Rewards are the agent's own. The instance leases its port like every
Unity instance here and ends in ``close()``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium import spaces
from mlagents_envs.base_env import ActionTuple, BehaviorSpec
from pettingzoo import ParallelEnv

from gymnasium_adapters.env import _allocator, _config
from gymnasium_adapters.slots import (
    DEFAULT_MAX_EXCHANGES,
    action_space,
    observation_space,
    sensor_keys,
    to_action_tuple,
)
from rollout.environment.ports import PortAllocator, PortRange
from rollout.environment.unity import UnityConfig, UnityError, UnityInstance


class UnityParallelEnv(ParallelEnv):
    metadata = {"name": "unity_rollout_parallel_v0", "render_modes": []}

    def __init__(
        self,
        build: str | UnityConfig | None = None,
        seed: int | None = None,
        port_range: PortRange | str | None = None,
        allocator: PortAllocator | None = None,
        max_exchanges: int = DEFAULT_MAX_EXCHANGES,
        **config: Any,
    ) -> None:
        self.config = _config(build, seed, **config)
        self.allocator = _allocator(allocator, port_range)
        self.max_exchanges = max_exchanges
        self.unity: UnityInstance | None = None
        self.agents: list[str] = []
        self.possible_agents: list[str] = []
        self._episodes: dict[tuple[str, int], int] = {}  # (behavior, id) -> episodes ended
        self._waiting: dict[str, tuple[str, int]] = {}  # name -> (behavior, row) this round
        self._last: dict[str, tuple[Any, dict[str, Any]]] = {}  # name -> last obs, info
        self._specs: dict[str, BehaviorSpec] = {}
        self._space_cache: dict[str, tuple[spaces.Space, spaces.Space]] = {}
        self._start(self.config)

    # --- spaces -------------------------------------------------------------------------

    def _spaces(self, behavior: str) -> tuple[spaces.Space, spaces.Space]:
        """A behavior's spaces, made once: PettingZoo wants the very same objects."""
        if behavior not in self._space_cache:
            spec = self._specs[behavior]
            self._space_cache[behavior] = (observation_space(spec), action_space(spec))
        return self._space_cache[behavior]

    def observation_space(self, agent: str) -> spaces.Space:
        return self._spaces(behavior_of(agent))[0]

    def action_space(self, agent: str) -> spaces.Space:
        return self._spaces(behavior_of(agent))[1]

    # --- the API ------------------------------------------------------------------------

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
        """A seed restarts the player with it (Unity seeds only at launch)."""
        if seed is not None and seed != self.config.seed:
            self.close()
            self.config = _config(self.config, seed)
            self._start(self.config)
        else:
            self._require().reset()
        self.agents = []
        self._waiting = {}
        self._last = {}
        self._episodes.clear()
        obs, _, _, _, infos = self._exchange(step_first=False)
        return obs, infos

    def step(
        self, actions: Mapping[str, Any]
    ) -> tuple[dict[str, Any], dict[str, float], dict[str, bool], dict[str, bool], dict]:
        unity = self._require()
        for behavior, spec in self._specs.items():
            rows = {row: a for a, (b, row) in self._waiting.items() if b == behavior}
            if not rows:
                continue
            chosen = [actions.get(rows[row]) for row in range(len(rows))]
            unity.set_actions(behavior, self._actions(behavior, spec, chosen))
        return self._exchange(step_first=True)

    def close(self) -> None:
        if self.unity is not None:
            unity, self.unity = self.unity, None
            unity.close()

    def state(self) -> np.ndarray:
        raise NotImplementedError("Unity builds expose no global state")

    # --- internals ----------------------------------------------------------------------

    def _start(self, config: UnityConfig) -> None:
        self.unity = UnityInstance(config, self.allocator)
        self.unity.start()
        try:
            self.unity.reset()
            self._specs.update(self.unity.behavior_specs)
        except BaseException:
            self.close()
            raise

    def _require(self) -> UnityInstance:
        if self.unity is None:
            raise UnityError("the environment is closed")
        return self.unity

    def _actions(self, behavior: str, spec: BehaviorSpec, chosen: list[Any]) -> ActionTuple:
        """One action per deciding agent, in Unity's row order; an agent without one
        (PettingZoo lets a policy skip) gets zeros."""
        space = self._spaces(behavior)[1]
        filled = [_zeros(space) if a is None else a for a in chosen]
        if isinstance(space, spaces.Dict):
            batch: Any = {k: np.stack([np.asarray(a[k]) for a in filled]) for k in space}
        else:
            batch = np.stack([np.asarray(a) for a in filled])
        return to_action_tuple(batch, space, spec, len(filled), batched=True)

    def _exchange(self, step_first: bool) -> tuple[dict, dict, dict, dict, dict]:
        """Exchange until an agent decides or ends; what PettingZoo's step returns."""
        unity = self._require()
        obs: dict[str, Any] = {}
        rewards: dict[str, float] = {}
        terminated: dict[str, bool] = {}
        truncated: dict[str, bool] = {}
        infos: dict[str, dict[str, Any]] = {}
        for _ in range(self.max_exchanges):
            if step_first:
                unity.step()
                unity.healthy_step()
            step_first = True
            self._waiting = {}
            self._specs.update(unity.behavior_specs)  # a build may add behaviors later
            for behavior in self._specs:
                decisions, terminals = unity.get_steps(behavior)
                keys = sensor_keys(self._specs[behavior])
                for row, agent_id in enumerate(terminals.agent_id):
                    name = self._name(behavior, int(agent_id))
                    if name not in self.agents:
                        continue  # ended before it ever decided: never one of ours
                    obs[name] = _obs([o[row] for o in terminals.obs], keys)
                    rewards[name] = rewards.get(name, 0.0) + float(terminals.reward[row])
                    truncated[name] = bool(terminals.interrupted[row])
                    terminated[name] = not truncated[name]
                    infos[name] = _info(behavior, terminals, row)
                    self.agents.remove(name)
                    self._episodes[(behavior, int(agent_id))] = (
                        self._episode(behavior, agent_id) + 1
                    )
                mask = _masks(decisions, self._specs[behavior])
                for row, agent_id in enumerate(decisions.agent_id):
                    name = self._name(behavior, int(agent_id))
                    if name not in self.agents:
                        self.agents.append(name)
                        if name not in self.possible_agents:
                            self.possible_agents.append(name)
                    obs[name] = _obs([o[row] for o in decisions.obs], keys)
                    rewards[name] = rewards.get(name, 0.0) + float(decisions.reward[row])
                    terminated.setdefault(name, False)
                    truncated.setdefault(name, False)
                    infos[name] = _info(behavior, decisions, row, mask)
                    self._waiting[name] = (behavior, row)
            if self._waiting or obs:
                break
        else:
            raise UnityError(f"no agent decided in {self.max_exchanges} exchanges with Unity")
        for name in self.agents:  # alive, silent this exchange: as they were
            if name not in obs and name in self._last:
                obs[name], infos[name] = self._last[name]
                rewards[name], terminated[name], truncated[name] = 0.0, False, False
        self._last = {n: (obs[n], infos[n]) for n in self.agents if n in obs}
        return obs, rewards, terminated, truncated, infos

    def _episode(self, behavior: str, agent_id: int | np.integer) -> int:
        return self._episodes.get((behavior, int(agent_id)), 0)

    def _name(self, behavior: str, agent_id: int) -> str:
        episode = self._episode(behavior, agent_id)
        return f"{behavior}?agent_id={agent_id}" + (f"&episode={episode}" if episode else "")


def behavior_of(agent: str) -> str:
    """The behavior of an agent's name (``"3DBall?team=0?agent_id=4"`` -> ``"3DBall?team=0"``)."""
    return agent.rsplit("?agent_id=", 1)[0]


def _zeros(space: spaces.Space) -> Any:
    if isinstance(space, spaces.Dict):
        return {k: np.zeros(s.shape, s.dtype) for k, s in space.items()}
    return np.zeros(space.shape, space.dtype)


def _obs(arrays: list[np.ndarray], keys: list[str]) -> Any:
    arrays = [np.asarray(a, np.float32).copy() for a in arrays]
    return arrays[0] if len(arrays) == 1 else dict(zip(keys, arrays, strict=True))


def _masks(decisions: Any, spec: BehaviorSpec) -> np.ndarray | None:
    size = int(sum(spec.action_spec.discrete_branches))
    if not size:
        return None
    if decisions.action_mask is None:
        return np.ones((len(decisions), size), np.bool_)
    return ~np.concatenate(decisions.action_mask, axis=1)


def _info(behavior: str, steps: Any, row: int, mask: np.ndarray | None = None) -> dict[str, Any]:
    info: dict[str, Any] = {
        "behavior": behavior,
        "group_id": int(np.asarray(steps.group_id)[row]),
        "group_reward": float(steps.group_reward[row]),
    }
    if mask is not None:
        info["action_mask"] = mask[row]
    return info
