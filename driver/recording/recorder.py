"""Who acts while a demonstration is recorded, and what is recorded of each step.

Actors (one per behavior of the build): a checkpoint's trained policy, a unitysim
environment's scripted expert (``unitysim.experts``), or uniform random actions for the
behaviors nobody trained. Each returns the actions *as Unity receives them* (continuous
actions clamped and scaled as the collector sends them), since that is what the agent did.

:class:`StepRecorder` turns one behavior's terminal and decision steps into
:class:`demonstrations.DemoStep` records the way Unity's ``DemonstrationRecorder`` does
(``Agent.SendInfoToBrain`` / ``NotifyAgentDone``): every decision and every episode end of
every agent, with its observations, reward, done, max_step_reached, agent id and action
mask. Unity stores with a step the agent's stored actions at that moment, which are the
actions of its *previous* decision (zeros at an episode's first step; a done step keeps
the last one): ``actions="unity"`` copies that, so a demo recorded here trains a BC or GAIL
learner as one recorded in Unity would. ``actions="decided"`` stores the action decided at
the step instead.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal, Protocol

import numpy as np
from mlagents_envs.base_env import ActionTuple, BehaviorSpec, DecisionSteps, TerminalSteps

from demonstrations import DemoStep
from learners.networks.policies import ActorCritic, TorchActor
from rollout.collecting.decisions import allowed_mask
from unitysim.experts import Expert

KEPT = 65_536  # agents remembered at most: one that vanished without an episode end goes


class AgentMemories:
    """A recorded policy's memories ``[memory_size]`` by agent id (a worker keeps them in
    its segment builder's slots); an agent never seen (or forgotten) has zeros."""

    def __init__(self, size: int, kept: int = KEPT) -> None:
        self.size, self.kept = size, kept
        self._by_agent: OrderedDict[int, np.ndarray] = OrderedDict()  # least recent first

    def __len__(self) -> int:
        return len(self._by_agent)

    def get(self, agents: np.ndarray) -> np.ndarray:
        """``[n, size]`` float32: each agent's memory, zeros for one without."""
        out = np.zeros((len(agents), self.size), np.float32)
        for row, agent in enumerate(agents.tolist()):
            if (memory := self._by_agent.get(agent)) is not None:
                out[row] = memory
        return out

    def put(self, agents: np.ndarray, memories: np.ndarray) -> None:
        for agent, memory in zip(agents.tolist(), memories, strict=True):
            self._by_agent[agent] = memory
            self._by_agent.move_to_end(agent)
        while len(self._by_agent) > self.kept:
            self._by_agent.popitem(last=False)

    def forget(self, agents: np.ndarray) -> None:
        """Agents whose episode ended: their next decision starts from zeros."""
        for agent in agents.tolist():
            self._by_agent.pop(agent, None)


class StepActor(Protocol):
    """Acts for one behavior's deciding agents; hears which agents' episodes ended."""

    def act(self, decisions: DecisionSteps) -> ActionTuple: ...

    def ended(self, agent_ids: Sequence[int]) -> None: ...


def _mask(decisions: DecisionSteps, spec: BehaviorSpec) -> np.ndarray | None:
    branches = spec.action_spec.discrete_branches
    return allowed_mask(decisions, sum(branches)) if branches else None


class PolicyActor:
    """A checkpoint's network, deterministic (its mean, its likeliest action) unless asked
    to sample; observations fed by the checkpoint's sensor names, in spec order."""

    def __init__(self, network: ActorCritic, stochastic: bool) -> None:
        network.settings = replace(network.settings, deterministic=not stochastic)
        self.actor = TorchActor(network)
        self.names = list(network.sensor_names)
        self.spec = network.spec
        # a policy with memory: each agent's, as a worker keeps them
        self.memories = AgentMemories(network.memory_size) if network.memory_size else None

    def act(self, decisions: DecisionSteps) -> ActionTuple:
        import torch

        pairs = zip(self.names, decisions.obs, strict=True)
        obs = {name: np.asarray(o, np.float32) for name, o in pairs}
        agents = np.asarray(decisions.agent_id, np.int64)
        memory = None if self.memories is None else self.memories.get(agents)
        with torch.no_grad():
            continuous, discrete, _, after = self.actor.act_recurrent(
                obs, _mask(decisions, self.spec), memory
            )
        if self.memories is not None and after is not None:
            self.memories.put(agents, after)
        return ActionTuple(self.actor.to_unity(continuous), discrete.astype(np.int32))

    def ended(self, agent_ids: Sequence[int]) -> None:
        if self.memories is not None:
            self.memories.forget(np.asarray(agent_ids, np.int64))


class ExpertActor:
    """A unitysim scripted expert, of a discrete or a continuous behavior."""

    def __init__(self, expert: Expert, spec: BehaviorSpec) -> None:
        self.expert, self.spec = expert, spec

    def act(self, decisions: DecisionSteps) -> ActionTuple:
        chosen = self.expert.act(np.asarray(decisions.agent_id), decisions.obs)
        n, action = len(decisions), self.spec.action_spec
        if action.continuous_size:
            return ActionTuple(chosen.astype(np.float32), np.zeros((n, 0), np.int32))
        return ActionTuple(np.zeros((n, 0), np.float32), chosen.astype(np.int32))

    def ended(self, agent_ids: Sequence[int]) -> None:
        self.expert.forget(agent_ids)


class RandomActor:
    """Uniform random actions (continuous in [-1, 1], discrete among the allowed ones):
    the agents of behaviors the checkpoint has no policy for."""

    def __init__(self, spec: BehaviorSpec, seed: int) -> None:
        self.spec, self.rng = spec, np.random.default_rng(seed)

    def act(self, decisions: DecisionSteps) -> ActionTuple:
        n, action = len(decisions), self.spec.action_spec
        continuous = self.rng.uniform(-1, 1, (n, action.continuous_size)).astype(np.float32)
        allowed = _mask(decisions, self.spec)
        picks, offset = [], 0
        for size in action.discrete_branches:
            ok = allowed[:, offset : offset + size] if allowed is not None else np.ones((n, size))
            offset += size
            weights = self.rng.random((n, size)) * ok
            picks.append(weights.argmax(axis=1))
        discrete = np.stack(picks, axis=1) if picks else np.zeros((n, 0))
        return ActionTuple(continuous, discrete.astype(np.int32))

    def ended(self, agent_ids: Sequence[int]) -> None:
        pass


@dataclass
class StepRecorder:
    """One behavior's records, in the order Unity writes them: each message's episode
    ends first (``NotifyAgentDone``), then its decisions (``SendInfoToBrain``)."""

    spec: BehaviorSpec
    actions: Literal["unity", "decided"] = "unity"
    steps: list[DemoStep] = field(default_factory=list)
    episodes: int = 0
    _last: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    _masks: dict[int, np.ndarray] = field(default_factory=dict)

    def _none(self) -> tuple[np.ndarray, np.ndarray]:
        action = self.spec.action_spec
        return (
            np.zeros(action.continuous_size, np.float32),
            np.zeros(len(action.discrete_branches), np.int32),
        )

    def _step(self, steps: Any, row: int, action: tuple[np.ndarray, np.ndarray], **kw: Any) -> None:
        agent = int(steps.agent_id[row])
        self.steps.append(
            DemoStep(
                observations=tuple(o[row] for o in steps.obs),
                reward=float(steps.reward[row]),
                agent_id=agent,
                continuous=action[0],
                discrete=action[1],
                group_id=int(steps.group_id[row]),
                group_reward=float(steps.group_reward[row]),
                **kw,
            )
        )

    def terminal(self, terminals: TerminalSteps, room: int) -> int:
        """Records up to ``room`` episode ends; how many it recorded."""
        count = min(room, len(terminals))
        for row in range(count):
            agent = int(terminals.agent_id[row])
            kept = self._last.pop(agent, None) if self.actions == "unity" else None
            self._step(
                terminals,
                row,
                kept or self._none(),
                done=True,
                interrupted=bool(terminals.interrupted[row]),
                action_mask=self._masks.pop(agent, np.zeros(0, bool)),  # Unity's last one
            )
            self.episodes += 1
        for row in range(count, len(terminals)):
            self._last.pop(int(terminals.agent_id[row]), None)
        return count

    def decisions(self, decisions: DecisionSteps, taken: ActionTuple, room: int) -> int:
        """Records up to ``room`` decisions, ``taken`` the actions sent for them."""
        masks = (
            np.concatenate(decisions.action_mask, axis=1)
            if decisions.action_mask is not None and self.spec.action_spec.discrete_branches
            else np.zeros((len(decisions), 0), bool)
        )
        for row in range(len(decisions)):
            agent = int(decisions.agent_id[row])
            action = (taken.continuous[row].copy(), taken.discrete[row].copy())
            stored = self._last.get(agent, self._none()) if self.actions == "unity" else action
            self._last[agent] = action
            self._masks[agent] = masks[row]
            if row < room:
                self._step(decisions, row, stored, action_mask=masks[row])
        return min(room, len(decisions))
