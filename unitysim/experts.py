"""Scripted experts for unitysim environments: what a real agent's ``Heuristic()`` would
play, for recording demonstrations (``unity-rollout record-demo --heuristic``).

Why trainer-side policies and not the player acting on its own: an expert here sees only
what the agent's sensors report (the observations Python receives) and returns the actions
Python sends, so the action recorded with each step *is* the action taken, by
construction, with no side channel to keep in step with the protocol, and it drives a
unitysim player exactly as any policy does. An expert that used the simulator's hidden
state could also demonstrate what no learner can imitate from the observations; this one
cannot. The price is memory kept per agent id (Hallway's symbol, Pyramids' search), which
:meth:`Expert.forget` drops when an agent's episode ends, as a Unity agent resets its own
fields in ``OnEpisodeBegin``.

Each expert plays one behavior, for discrete actions only (both examples have one branch
of 5: none, forward, back, turn right, turn left). Ray sensors are read as
``unitysim.envs.perception`` lays them out (and RayPerceptionSensor does): per ray a one-hot
tag, a "missed" flag and the hit fraction; rays ahead first, then right/left pairs.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence

import numpy as np

from unitysim.envs.hallway import RAY_LENGTH
from unitysim.envs.pyramids import RAY

NOOP, FORWARD, BACK, RIGHT, LEFT = range(5)


def rays(observation: np.ndarray, num_tags: int) -> tuple[np.ndarray, np.ndarray]:
    """(tag seen per ray, -1 for none; hit fraction per ray) of one ray sensor, batched."""
    width = num_tags + 2
    per_ray = observation.reshape(len(observation), observation.shape[-1] // width, width)
    onehot = per_ray[:, :, :num_tags] > 0.5
    tag = np.where(onehot.any(axis=2), onehot.argmax(axis=2), -1)
    return tag, per_ray[:, :, num_tags + 1]


def toward(seen: np.ndarray) -> int | None:
    """Which way to go for a target seen by the rays marked in ``seen`` (Unity's ray order:
    ahead, then right/left pairs): forward when ahead, else turn to the nearest side."""
    hits = np.flatnonzero(seen)
    if len(hits) == 0:
        return None
    first = int(hits[0])
    if first == 0:
        return FORWARD
    return RIGHT if first % 2 == 1 else LEFT


class Expert(ABC):
    """A scripted policy for one behavior: observations in, discrete actions out.

    Rays are 18 degrees of turn per decision apart from where they were, and 23 to 30
    degrees apart from each other, so a target seen by a side ray is out of sight after
    the turn toward it: an expert keeps walking toward where it last saw its target for a
    few decisions (the bearing grows as it nears, and a side ray finds it again), and
    only then looks around, turning toward the side it last saw it on. A target that
    jumps from one side ray to the other after a turn lies between them: straight on.
    """

    RECENT = 8  # decisions a target out of sight is still walked toward
    SCAN = 22  # then turns in place (a full circle takes 20 decisions), then walks a bit

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.unseen: dict[int, int] = {}  # agent -> decisions since its target was seen
        self.side: dict[int, int] = {}  # agent -> the way it last turned toward its target
        self.turned: dict[int, int] = {}  # agent -> its last move toward a target in sight

    @abstractmethod
    def act(self, agent_ids: np.ndarray, observations: Sequence[np.ndarray]) -> np.ndarray:
        """Actions (n, 1) int32 for the agents deciding now; ``observations`` one array per
        sensor, batched as ``DecisionSteps.obs``."""

    def forget(self, agent_ids: Sequence[int]) -> None:
        """These agents' episodes ended: what was remembered of them goes."""
        for agent in (int(a) for a in agent_ids):
            for memory in self.memories():
                memory.pop(agent, None)

    def memories(self) -> list[dict[int, int]]:
        return [self.unseen, self.side, self.turned]

    def home(self, agent: int, seen: np.ndarray | None, wall_close: bool) -> int:
        """The action toward a target seen by the rays marked in ``seen`` (None: no target
        known yet), walking on toward where it was or looking around when it is not."""
        move = None if seen is None else toward(seen)
        if move is not None:
            self.unseen[agent] = 0
            if move != FORWARD:
                if self.turned.get(agent) == RIGHT + LEFT - move:  # it is between two rays
                    move = FORWARD
                else:
                    self.side[agent] = move
            self.turned[agent] = move
            return move
        self.turned[agent] = NOOP
        spent = self.unseen.get(agent, self.RECENT) + 1
        self.unseen[agent] = spent
        side = self.side.get(agent, LEFT)
        if spent <= self.RECENT:
            return side if wall_close else FORWARD
        cycle = (spent - self.RECENT) % (self.SCAN + self.WALK)
        if cycle < self.SCAN or wall_close:
            return side
        return FORWARD

    WALK = 6  # decisions walked between two looks around


class HallwayExpert(Expert):
    """Hallway: find the symbol (look around until a ray sees a block) and remember its
    colour; face the symbol, turn about, and walk down the hallway (steering toward the
    freest of the rays ahead) until the goal of that colour is in sight; then go to it."""

    ORANGE_GOAL, RED_GOAL, ORANGE_BLOCK, RED_BLOCK, WALL = range(5)
    ABOUT_TURN = 10  # decisions of turning: half a circle

    def __init__(self, seed: int = 0) -> None:
        super().__init__(seed)
        self.goal: dict[int, int] = {}  # agent -> the tag of the goal to reach
        self.turning: dict[int, int] = {}  # agent -> decisions of its about-turn left
        self.away: dict[int, int] = {}  # agent -> the turn away from the other goal
        self.spun: dict[int, int] = {}  # agent -> decisions looking for the wanted goal
        self.since: dict[int, int] = {}  # agent -> decisions since it saw the wanted goal

    def memories(self) -> list[dict[int, int]]:
        return [*super().memories(), self.goal, self.turning, self.away, self.spun, self.since]

    def act(self, agent_ids: np.ndarray, observations: Sequence[np.ndarray]) -> np.ndarray:
        frame = observations[0][:, -35:]  # the newest of the 3 stacked frames
        tags, fractions = rays(frame, 5)
        actions = np.zeros((len(agent_ids), 1), np.int32)
        for row, agent in enumerate(int(a) for a in agent_ids):
            tag = tags[row]
            blocks = (tag == self.ORANGE_BLOCK) | (tag == self.RED_BLOCK)
            wall_close = fractions[row, 0] * RAY_LENGTH < 1.0
            if agent not in self.goal:
                if blocks.any():
                    orange = (tag == self.ORANGE_BLOCK).any()
                    self.goal[agent] = self.ORANGE_GOAL if orange else self.RED_GOAL
                else:
                    actions[row, 0] = self.home(agent, None, wall_close)
                    continue
            wanted = tag == self.goal[agent]
            since = self.since[agent] = 0 if wanted.any() else self.since.get(agent, 99) + 1
            if since <= self.RECENT:  # the goal in sight, or just lost: walk on toward it
                actions[row, 0] = self.home(agent, wanted, wall_close)
            elif agent not in self.turning:  # face the symbol first
                if blocks[0]:
                    self.turning[agent] = self.ABOUT_TURN
                actions[row, 0] = self.home(agent, blocks, wall_close)
            elif self.turning[agent] > 0:
                self.turning[agent] -= 1
                actions[row, 0] = LEFT
            elif (other := (tag >= 0) & (tag <= self.RED_GOAL) & ~wanted).any():
                # the other goal: the wanted one is across the hallway's end; look around
                # (away from it first), walking on a little after each full circle
                if agent not in self.away:
                    self.away[agent] = LEFT if toward(other) == RIGHT else RIGHT
                spun = self.spun[agent] = self.spun.get(agent, 0) + 1
                actions[row, 0] = self.away[agent] if spun % 26 < 20 else FORWARD
            elif blocks[:3].any() or wall_close:  # back toward the symbol, or stuck: about
                self.turning[agent] = self.ABOUT_TURN - 1
                actions[row, 0] = LEFT
            else:  # down the hallway: toward the freest of the rays ahead
                free = fractions[row, :3]
                best = int(free.argmax())
                ahead = free[best] - free[0] < 0.05
                actions[row, 0] = FORWARD if ahead else (RIGHT, LEFT)[best - 1]
        return actions


class PyramidsExpert(Expert):
    """Pyramids: while the switch is off, go to it (seen by the rays ahead or behind);
    once on, go to the pyramid (the gold seen by the high rays, its bricks by the low
    ones). Nothing in sight: look around, then walk toward the freest ray ahead (an
    opening to the next room), turning off walls and stones."""

    BLOCK, WALL, GOAL, SWITCH_OFF, SWITCH_ON, STONE = range(6)
    WALK = 20  # the agent is fast (4.5 per decision): long walks reach other rooms

    def act(self, agent_ids: np.ndarray, observations: Sequence[np.ndarray]) -> np.ndarray:
        ahead, ahead_fraction = rays(observations[0], 6)
        behind, _ = rays(observations[1], 6)
        above, _ = rays(observations[2], 6)
        switched = observations[3][:, 0] > 0.5
        actions = np.zeros((len(agent_ids), 1), np.int32)
        for row, agent in enumerate(int(a) for a in agent_ids):
            if switched[row]:
                seen = above[row] == self.GOAL
                if not seen.any():
                    seen = ahead[row] == self.BLOCK
                in_back = (behind[row] == self.BLOCK).any()
            else:
                seen = ahead[row] == self.SWITCH_OFF
                in_back = (behind[row] == self.SWITCH_OFF).any()
            if not seen.any() and in_back:
                self.side[agent] = LEFT  # turn around toward it
                self.unseen[agent] = self.RECENT + 1
            wall_close = bool(ahead_fraction[row, 0] * RAY < 6.0)
            move = self.home(agent, seen, wall_close)
            free = ahead_fraction[row]
            best = int(free.argmax())
            if move == FORWARD and not seen.any() and free[best] - free[0] > 0.2:
                move = RIGHT if best % 2 == 1 else LEFT  # toward open space: a door
            actions[row, 0] = move
        return actions


EXPERTS: dict[str, Callable[[int], Expert]] = {
    "Hallway?team=0": HallwayExpert,
    "Pyramids?team=0": PyramidsExpert,
}


def expert_for(behavior: str, seed: int = 0) -> Expert | None:
    """The scripted expert of a unitysim behavior (its full name), or None when it has none."""
    make = EXPERTS.get(behavior)
    return make(seed) if make is not None else None
