"""Echo: a test environment for the rollout side, not an ML-Agents example.

Every agent's observation echoes the last action applied to it, so a test can prove that each
action reached the agent it was sampled for, across the hard cases of the protocol: agents that
appear and leave, agents that switch behaviors, terminal and decision infos of one agent in
one message, and agents that skip a decision.

Two behaviors with the same hybrid action spec (2 continuous, branches (3, 2)): ``EchoA?team=0``
(behavior index 0) and ``EchoB?team=0`` (index 1). Each has one vector sensor ``"Echo"`` of
size 8; the observation of an agent is::

    [0] agent id
    [1] episode index of this agent (0 for its first episode)
    [2] step index: environment steps since this episode began (0 at episode start)
    [3:5] last continuous action applied to the agent (zeros at episode start), unclipped
    [5:7] last discrete actions applied to the agent, as floats (zeros at episode start)
    [7] behavior index of the row (0 for EchoA, 1 for EchoB)

The reward of every row, terminal or decision, is ``float32(0.01 * step index)``. The action
mask forbids discrete action 2 of branch 0 for agents with odd ids (nothing else is masked).

Each area starts with 4 agents, ids from a counter that never repeats, alternately under A and
B (all under A with parameter ``start_all_a`` = 1, so that EchoB first appears later). Every
step, every agent advances one step, then, drawing everything from ``rng``:

- with ``end_prob`` (0.05) its episode ends: a done row (``max_step_reached`` with probability
  ``interrupt_prob``, 0.3), then, in the same message, a decision row with the same id for its
  next episode; or, with probability ``leave_prob`` (0.2), it leaves for good instead (the
  population never drops below ``num_areas`` agents);
- otherwise, with ``switch_prob`` (0.02) it switches behavior: a done, interrupted row under
  the old behavior, then a decision row of a new episode under the new one, same id;
- each area, with ``spawn_prob`` (0.03), gains an agent with a new id and a random behavior
  (at most 8 * ``num_areas`` agents in all);
- with ``skip_prob`` (0.05) an agent does not request a decision this step: it has no
  decision row and gets no action; its last action stays in place.

Rows of a behavior come as terminal rows, then decision rows, each in slot order (slots of
agents that left are reused, so a new agent can sit between old ones). A message with no rows
at all is never sent: the simulation runs on until some agent reports; a behavior without rows
is left out of the output. On ``reset`` the agents stay, each starts a new episode, and no
terminal rows are sent, as in Unity.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from unitysim.envs.base import (
    Actions,
    AgentInfos,
    Behavior,
    Output,
    Parameters,
    Sensor,
    SimEnv,
    StatsMethod,
)

CONTINUOUS = 2
BRANCHES = (3, 2)
OBS_SIZE = 8
START_PER_AREA = 4
MAX_PER_AREA = 8
REWARD_PER_STEP = 0.01
DEFAULTS = {
    "end_prob": 0.05,
    "interrupt_prob": 0.3,
    "leave_prob": 0.2,
    "switch_prob": 0.02,
    "spawn_prob": 0.03,
    "skip_prob": 0.05,
}


def _behavior(name: str) -> Behavior:
    return Behavior(
        f"{name}?team=0", (Sensor.vector("Echo", OBS_SIZE),), CONTINUOUS, branches=BRANCHES
    )


class Echo(SimEnv):
    name = "Echo"
    behaviors = (_behavior("EchoA"), _behavior("EchoB"))

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        capacity = MAX_PER_AREA * self.num_areas
        self.alive = np.zeros(capacity, dtype=bool)
        self.ids = np.zeros(capacity, dtype=np.int64)
        self.kind = np.zeros(capacity, dtype=np.int64)  # behavior index
        self.episode = np.zeros(capacity, dtype=np.int64)
        self.steps = np.zeros(capacity, dtype=np.int64)
        self.continuous = np.zeros((capacity, CONTINUOUS), dtype=np.float32)
        self.discrete = np.zeros((capacity, len(BRANCHES)), dtype=np.int64)
        self.next_id = 0
        # slots of the decision rows last reported, per behavior index, in row order
        self.reported: list[np.ndarray] = [np.zeros(0, dtype=np.int64)] * len(self.behaviors)

    # --- agents ----------------------------------------------------------------------

    def _spawn(self, slots: np.ndarray, kinds: np.ndarray) -> None:
        """New agents with new ids, in their first episode."""
        self.alive[slots] = True
        self.ids[slots] = np.arange(self.next_id, self.next_id + len(slots))
        self.next_id += len(slots)
        self.kind[slots] = kinds
        self.episode[slots] = -1
        self._begin_episodes(slots)

    def _begin_episodes(self, slots: np.ndarray) -> None:
        self.episode[slots] += 1
        self.steps[slots] = 0
        self.continuous[slots] = 0.0
        self.discrete[slots] = 0

    def _observe(self) -> np.ndarray:
        """The observation of every slot, (capacity, 8); see the module docstring."""
        return np.column_stack(
            [self.ids, self.episode, self.steps, self.continuous, self.discrete, self.kind]
        ).astype(np.float32)

    @staticmethod
    def _rows(obs: np.ndarray, **kwargs: np.ndarray | bool) -> AgentInfos:
        """Infos of some observation rows; id, reward and mask follow from the observation."""
        ids = obs[:, 0].astype(np.int64)
        mask = np.zeros((len(obs), sum(BRANCHES)), dtype=bool)
        mask[:, 2] = ids % 2 == 1
        reward = (REWARD_PER_STEP * obs[:, 2].astype(np.float64)).astype(np.float32)
        return AgentInfos.build(ids, [obs], reward, action_mask=mask, **kwargs)

    # --- the contract ----------------------------------------------------------------

    def reset(self) -> Output:
        if not self.alive.any():
            start = START_PER_AREA * self.num_areas
            all_a = self.params.get("start_all_a", 0.0) >= 0.5
            kinds = np.zeros(start, dtype=np.int64) if all_a else np.arange(start) % 2
            self._spawn(np.arange(start), kinds)
        else:
            self._begin_episodes(np.flatnonzero(self.alive))
        nobody = np.zeros(0, dtype=np.int64)
        return self._output(self._observe(), self.kind, nobody, self.alive, self.alive.copy())

    def step(self, actions: Mapping[str, Actions]) -> Output:
        for index, behavior in enumerate(self.behaviors):
            act = actions.get(behavior.name)
            if act is None or not len(act):
                continue
            slots = self.reported[index]
            if len(act) != len(slots):
                raise ValueError(
                    f"{behavior.name}: {len(act)} actions for {len(slots)} decision rows"
                )
            self.continuous[slots] = act.continuous
            self.discrete[slots] = act.discrete
        while True:
            output = self._simulate()
            if output:
                return output

    def _simulate(self) -> Output:
        """One environment step: advance, draw the events, and report."""
        p = {key: self.params.get(key, value) for key, value in DEFAULTS.items()}
        draws = self.rng.random((6, len(self.alive)))
        self.steps[self.alive] += 1

        ends = self.alive & (draws[0] < p["end_prob"])
        switches = self.alive & ~ends & (draws[1] < p["switch_prob"])
        wants_leave = ends & (draws[2] < p["leave_prob"])
        room = max(int(self.alive.sum()) - self.num_areas, 0)
        leaves = wants_leave & (np.cumsum(wants_leave) <= room)
        done = ends | switches
        interrupted = switches | (ends & (draws[3] < p["interrupt_prob"]))

        final = self._observe()  # the terminal rows' observations, before the transitions
        final_kind = self.kind.copy()
        self.alive[leaves] = False
        self.kind[switches] = 1 - self.kind[switches]
        self._begin_episodes(np.flatnonzero(done & ~leaves))
        spawns = int((self.rng.random(self.num_areas) < p["spawn_prob"]).sum())
        free = np.flatnonzero(~self.alive)[:spawns]
        if len(free):
            self._spawn(free, (draws[5, free] < 0.5).astype(np.int64))

        decide = self.alive & (draws[4] >= p["skip_prob"])
        ended = np.flatnonzero(done)
        if len(ended):  # StatsRecorder, so the Stats side channel has traffic to carry
            self.record_stat("Echo/Episodes Ended", len(ended), StatsMethod.SUM)
            self.record_stat("Echo/Agents Alive", int(self.alive.sum()), StatsMethod.MOST_RECENT)
        return self._output(final, final_kind, ended, interrupted, decide)

    def _output(
        self,
        final: np.ndarray,
        final_kind: np.ndarray,
        ended: np.ndarray,
        interrupted: np.ndarray,
        decide: np.ndarray,
    ) -> Output:
        """Per behavior: terminal rows of the slots ``ended``, then the decision rows."""
        output: Output = {}
        current = self._observe()
        for index, behavior in enumerate(self.behaviors):
            parts = []
            mine = ended[final_kind[ended] == index]
            if len(mine):
                parts.append(self._rows(final[mine], done=True, max_step_reached=interrupted[mine]))
            slots = np.flatnonzero(decide & (self.kind == index))
            self.reported[index] = slots
            if len(slots):
                parts.append(self._rows(current[slots]))
            if parts:
                output[behavior.name] = AgentInfos.concat(parts)
        return output
