"""Scripted experts for unitysim environments: what a real agent's ``Heuristic()`` would
play, for recording demonstrations (``unity-rollout record-demo --heuristic``).

Why trainer-side policies and not the player acting on its own: an expert here sees only
what the agent's sensors report (the observations Python receives) and returns the actions
Python sends, so the action recorded with each step *is* the action taken, by
construction, with no side channel to keep in step with the protocol, and it drives a
unitysim player exactly as any policy does. An expert that used the simulator's hidden
state could also demonstrate what no learner can imitate from the observations; this one
cannot. The price is memory kept per agent id (Hallway's symbol and bearings, Pyramids'
search), which :meth:`Expert.forget` drops when an agent's episode ends, as a Unity agent
resets its own fields in ``OnEpisodeBegin``.

Each expert plays one behavior. Hallway's and Pyramids' (:class:`RayExpert`) choose
among one branch of 5 actions (none, forward, back, turn right, turn left), PushBlock's
among 7 (strafe left and right too); ray sensors are read as ``unitysim.envs.perception``
lays them out (and RayPerceptionSensor does): per ray a one-hot tag, a "missed" flag and
the hit fraction; rays ahead first, then right/left pairs. Crawler's
(:class:`CrawlerExpert`) sets its 20 joint targets from the speed and turn its vector
sensor reports, as a Heuristic() written for the body would.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence

import numpy as np

from unitysim.envs import push_block
from unitysim.envs.crawlers import CRAWLER_SPEED, LEGS, Crawler
from unitysim.envs.hallway import RAY_LENGTH
from unitysim.envs.pyramids import RAY

# one branch of moves (arena.MOVES): none, forward, back, turn right, turn left, strafe left, right
NOOP, FORWARD, BACK, RIGHT, LEFT, STRAFE_LEFT, STRAFE_RIGHT = range(7)


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
    """A scripted policy for one behavior: observations in, actions out."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)

    @abstractmethod
    def act(self, agent_ids: np.ndarray, observations: Sequence[np.ndarray]) -> np.ndarray:
        """Actions for the agents deciding now, (n, branches) int32 for a discrete
        behavior, (n, size) float32 for a continuous one; ``observations`` one array per
        sensor, batched as ``DecisionSteps.obs``."""

    def forget(self, agent_ids: Sequence[int]) -> None:  # noqa: B027 (most remember nothing)
        """These agents' episodes ended: what was remembered of them goes."""


class RayExpert(Expert):
    """An expert that walks by one branch of moves to targets its ray sensors see.

    Rays are 18 degrees of turn per decision apart from where they were, and 23 to 35
    degrees apart from each other, so a target seen by a side ray is out of sight after
    the turn toward it: an expert keeps walking toward where it last saw its target for a
    few decisions (the bearing grows as it nears, and a side ray finds it again), and
    only then looks around, turning toward the side it last saw it on. A target that
    jumps from one side ray to the other after a turn lies between them: straight on.
    """

    RECENT = 8  # decisions a target out of sight is still walked toward
    SCAN = 22  # then turns in place (a full circle takes 20 decisions), then walks a bit

    def __init__(self, seed: int = 0) -> None:
        super().__init__(seed)
        self.unseen: dict[int, int] = {}  # agent -> decisions since its target was seen
        self.side: dict[int, int] = {}  # agent -> the way it last turned toward its target
        self.turned: dict[int, int] = {}  # agent -> its last move toward a target in sight

    def forget(self, agent_ids: Sequence[int]) -> None:
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


class HallwayExpert(RayExpert):
    """Hallway: look around a full circle, noting which ways are open as far as the rays
    reach (the hallway's axis: its side walls are in reach across it) and where the
    symbol is if in sight; else walk along the hallway until a ray sees it. Its colour
    tells the goal, and the way to it the hallway's far end: the goals are beyond it.
    Walk down the middle, rounding the symbol, until the goal of the symbol's colour is in
    sight; then go to it. Seeing only the other goal, brake and cross the hallway's end.

    The agent keeps its bearings by counting its own turns (each decision of turning is
    18 degrees, one "step" here) and its speed by its own pushes, as a player would."""

    ORANGE_GOAL, RED_GOAL, ORANGE_BLOCK, RED_BLOCK, WALL = range(5)
    RAY_STEPS = (0, -2, 2, -4, 4)  # the rays' directions (35 and 70 degrees), in turn steps
    CIRCLE = 20  # turn steps in a full circle
    ROUND = 4.0  # the symbol nearer than this ahead: turn off it, to pass it
    SLACK = 0.2  # the side walls' distances (fractions) may differ this much: "middle"
    BRAKE = 14.0  # speed (per second) above which it brakes before turning at the goals
    PUSH, KEEP = 9.0, 0.79  # a decision's push (velocity change), and the speed drag keeps

    def __init__(self, seed: int = 0) -> None:
        super().__init__(seed)
        self.goal: dict[int, int] = {}  # agent -> the tag of the goal to reach
        self.facing: dict[int, int] = {}  # agent -> its turns so far (steps, left positive)
        self.open: dict[int, list[bool]] = {}  # agent -> open ahead, per facing of its circle
        self.symbol: dict[int, int] = {}  # agent -> where it first saw the symbol (steps)
        self.down: dict[int, int] = {}  # agent -> the way down the hallway (steps)
        self.cross: dict[int, int] = {}  # agent -> the way across to the wanted goal
        self.speed: dict[int, float] = {}  # agent -> its speed along its facing, estimated
        self.since: dict[int, int] = {}  # agent -> decisions since it saw the wanted goal

    def memories(self) -> list[dict]:
        own = [self.goal, self.facing, self.open, self.symbol, self.down, self.cross]
        return [*super().memories(), *own, self.speed, self.since]

    def act(self, agent_ids: np.ndarray, observations: Sequence[np.ndarray]) -> np.ndarray:
        frame = observations[0][:, -35:]  # the newest of the 3 stacked frames
        tags, fractions = rays(frame, 5)
        actions = np.zeros((len(agent_ids), 1), np.int32)
        for row, agent in enumerate(int(a) for a in agent_ids):
            action = actions[row, 0] = self._act(agent, tags[row], fractions[row])
            turn = {LEFT: 1, RIGHT: -1}.get(action, 0)
            self.facing[agent] = self.facing.get(agent, 0) + turn
            push = {FORWARD: self.PUSH, BACK: -self.PUSH}.get(action, 0.0)
            self.speed[agent] = (self.speed.get(agent, 0.0) + push) * self.KEEP
        return actions

    def _act(self, agent: int, tag: np.ndarray, free: np.ndarray) -> int:
        """Rays: 0 ahead, 1 and 2 right and left at 35 degrees, 3 and 4 at 70."""
        blocks = (tag == self.ORANGE_BLOCK) | (tag == self.RED_BLOCK)
        facing, fast = self.facing.get(agent, 0), self.speed.get(agent, 0.0) > self.BRAKE
        if agent not in self.goal and blocks.any():
            orange = tag[blocks][0] == self.ORANGE_BLOCK
            self.goal[agent] = self.ORANGE_GOAL if orange else self.RED_GOAL
            self.symbol[agent] = facing + self.RAY_STEPS[int(np.flatnonzero(blocks)[0])]
        circle = self.open.setdefault(agent, [])
        if len(circle) < self.CIRCLE:  # the first look around
            circle.append(bool(free[0] >= 1.0))
            return LEFT
        if agent not in self.goal:  # along the hallway (open ahead, a side wall in reach)
            return FORWARD if free[0] >= 1.0 and min(free[3], free[4]) < 1.0 else LEFT
        if agent not in self.down:
            self.down[agent] = self.axis(circle, self.symbol[agent])
        wanted = tag == self.goal[agent]
        other = (tag >= 0) & (tag <= self.RED_GOAL) & ~wanted
        since = self.since[agent] = 0 if wanted.any() else self.since.get(agent, 99) + 1
        if since <= self.RECENT:  # the goal in sight, or just lost: to it
            if fast and not wanted[0]:
                return BACK
            return self.home(agent, wanted, free[0] * RAY_LENGTH < 1.0)
        walls = np.where(tag == self.WALL, free, 1.0)
        right, left = min(walls[1], walls[3]), min(walls[2], walls[4])  # the side walls
        if other.any() and agent not in self.cross:  # the wanted goal is across the end
            seen = self._wrap(facing + self.RAY_STEPS[int(np.flatnonzero(other)[0])])
            aside = self._wrap(seen - self.down[agent])  # > 0: on the left of the axis
            on_left = aside > 1 or (aside >= -1 and left < right)
            self.cross[agent] = self.down[agent] + (-5 if on_left else 5)  # 90 degrees
        if agent in self.cross:
            return BACK if fast else self.turn_to(agent, self.cross[agent])
        if blocks[:3].any() and free[:3][blocks[:3]].min() * RAY_LENGTH < self.ROUND:
            # round the symbol: off it while it is straight ahead, then on past it
            return self.side.setdefault(agent, LEFT) if blocks[0] else FORWARD
        off = abs(right - left)  # toward the middle: up to 54 degrees off the axis
        shift = min(3, int(off / self.SLACK))
        bearing = self.down[agent] + (shift if right < left else -shift)
        return self.turn_to(agent, bearing, slack=1)

    def axis(self, circle: list[bool], symbol: int) -> int:
        """The way down the hallway (steps): the middle of the run of open facings of the
        look around nearest the symbol's direction; with the opposite run (the way back)
        too, their mean, which cancels the lean both get from an agent off the middle."""
        runs, n = [], len(circle)
        for i in range(n):  # each run's start: open here, not just before
            if circle[i] and not circle[i - 1]:
                length = next((k for k in range(1, n) if not circle[(i + k) % n]), n)
                runs.append(i + (length - 1) / 2)
        if not runs:
            return symbol
        near = min(runs, key=lambda r: abs(self._wrap(r - symbol)))
        back = [r for r in runs if abs(self._wrap(r - near - n / 2)) <= 2]
        middle = near if not back else near + self._wrap(back[0] - near - n / 2) / 2
        return round(middle)

    def _wrap(self, steps: float) -> float:
        return (steps + self.CIRCLE / 2) % self.CIRCLE - self.CIRCLE / 2

    def turn_to(self, agent: int, bearing: int, slack: int = 0) -> int:
        """Toward ``bearing``: on when within ``slack`` steps of it, else turning."""
        off = self._wrap(bearing - self.facing.get(agent, 0))
        return FORWARD if abs(off) <= slack else (LEFT if off > 0 else RIGHT)


class PyramidsExpert(RayExpert):
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


class CrawlerExpert(Expert):
    """Crawler: turn towards the target and walk at the episode's speed. Its vector sensor
    gives the speed to match and the turn to the target direction; the pose that makes the
    body move that way follows from the body's fixed map (``Crawler.mix``), solved for the
    angles the actions set, at full strength."""

    TURN_GAIN = 2.0  # full turn rate beyond half a radian off the target direction
    # the pose entries the actions set: both angles of the upper legs, the first of the lower
    FREE = np.r_[0 : 2 * LEGS, 2 * LEGS : 4 * LEGS : 2]
    SOLVE = np.linalg.pinv(Crawler.mix[FREE])  # (3, 12): motion -> least-norm pose

    def act(self, agent_ids: np.ndarray, observations: Sequence[np.ndarray]) -> np.ndarray:
        vector = observations[1]
        speed = vector[:, 6]
        qy, qw = vector[:, 8], vector[:, 10]
        turn = 2.0 * np.arctan2(qy, qw)  # clockwise, from facing to the target direction
        stride = np.exp(-1j * turn) * speed / CRAWLER_SPEED  # forward + 1j * left
        motion = np.column_stack([stride.real, stride.imag, -turn * self.TURN_GAIN])
        pose = np.arctanh(np.clip(motion, -0.95, 0.95)) @ self.SOLVE
        strengths = np.ones((len(agent_ids), 2 * LEGS))
        return np.clip(np.concatenate([pose, strengths], axis=1), -1.0, 1.0).astype(np.float32)


class PushBlockExpert(Expert):
    """PushBlock: find the goal, then push the block into it without turning again.

    A full circle of turns (18 of 20 degrees) notes the turn at which the low ray ahead
    sees the goal strip nearest, and turns back to it: the agent then faces the goal.
    Never turning again, it keeps that bearing: a block ahead is pushed forward, a block
    ahead to a side is strafed towards until it is ahead. A block out of sight is first
    looked for ahead (walking towards the goal: the rays reach 12 of the court's 25); one
    level with the agent (the 90-degree rays), or none by the goal, is behind: walk back
    past it, sidestepping towards the middle now and then so as not to back into it, and
    after a while look ahead again. No goal in sight over a circle: walk a little, look
    again. An episode's end forgets it all (a real build turns the whole area)."""

    CIRCLE = 18  # turns of 20 degrees
    SIDESTEP = 12  # decisions walked back before a sidestep of as many
    WANDER = 6  # decisions walked when the goal was not seen over a circle
    NEAR_GOAL = 0.25  # of the rays' 12: the goal strip this near ahead
    GIVE_UP = 4 * SIDESTEP  # decisions walked back without finding the block

    def __init__(self, seed: int = 0) -> None:
        super().__init__(seed)
        self.turns: dict[int, int] = {}  # agent -> turns made while looking for the goal
        self.nearest: dict[int, tuple[float, int]] = {}  # agent -> (fraction, at turn)
        self.walked: dict[int, int] = {}  # agents facing the goal -> decisions walked back

    def forget(self, agent_ids: Sequence[int]) -> None:
        for agent in (int(a) for a in agent_ids):
            for memory in (self.turns, self.nearest, self.walked):
                memory.pop(agent, None)

    def act(self, agent_ids: np.ndarray, observations: Sequence[np.ndarray]) -> np.ndarray:
        width = push_block.RAYS.size
        low, low_fraction = rays(observations[1][:, -width:], push_block.RAYS.num_tags)
        actions = np.zeros((len(agent_ids), 1), np.int32)
        for row, agent in enumerate(int(a) for a in agent_ids):
            actions[row, 0] = self._act(agent, low[row], low_fraction[row])
        return actions

    def _act(self, agent: int, tags: np.ndarray, fractions: np.ndarray) -> int:
        if agent in self.walked:  # facing the goal
            return self._push(agent, tags, fractions)
        turns = self.turns.setdefault(agent, 0)
        if tags[0] == push_block.GOAL and fractions[0] < self.nearest.get(agent, (2.0, 0))[0]:
            self.nearest[agent] = (float(fractions[0]), turns % self.CIRCLE)
        if turns < self.CIRCLE:
            self.turns[agent] = turns + 1
            return LEFT
        if agent not in self.nearest:  # no goal in sight: walk, then look again
            if turns < self.CIRCLE + self.WANDER:
                self.turns[agent] = turns + 1
                return FORWARD
            self.turns[agent] = 0
            return LEFT
        if turns % self.CIRCLE != self.nearest[agent][1]:
            self.turns[agent] = turns + 1
            return LEFT
        self.walked[agent] = 0
        return self._push(agent, tags, fractions)

    def _push(self, agent: int, tags: np.ndarray, fractions: np.ndarray) -> int:
        seen = np.flatnonzero(tags == push_block.BLOCK)
        ray = int(seen[0]) if len(seen) else -1
        if ray == 0:
            return FORWARD
        if 0 < ray < 2 * push_block.RAYS.rays_per_direction - 1:  # ahead to a side
            return STRAFE_RIGHT if ray % 2 == 1 else STRAFE_LEFT
        near_goal = tags[0] == push_block.GOAL and fractions[0] < self.NEAR_GOAL
        walked = self.walked[agent]
        if ray < 0 and walked == 0 and not near_goal:
            return FORWARD  # out of reach ahead, or behind: first look ahead
        # level with the agent, or behind it: walk back past it, sidestepping now and then
        walked = self.walked[agent] = (walked + 1) % self.GIVE_UP  # then look ahead again
        if (walked // self.SIDESTEP) % 2 == 1:
            right, left = fractions[-2], fractions[-1]  # the 90-degree rays: the side walls
            return STRAFE_LEFT if left >= right else STRAFE_RIGHT
        return BACK


EXPERTS: dict[str, Callable[[int], Expert]] = {
    "Hallway?team=0": HallwayExpert,
    "Pyramids?team=0": PyramidsExpert,
    "Crawler?team=0": CrawlerExpert,
    "PushBlock?team=0": PushBlockExpert,
}


def expert_for(behavior: str, seed: int = 0) -> Expert | None:
    """The scripted expert of a unitysim behavior (its full name), or None when it has none."""
    make = EXPERTS.get(behavior)
    return make(seed) if make is not None else None
