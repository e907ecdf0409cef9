"""Self-play as mlagents-learn 1.1.0 runs it (its ghost trainer and ghost controller), in
the central learner, so that every worker plays by the same rules.

- **Teams** are the ``?team=N`` of behavior ids. One team learns at a time; the teams take
  turns (the controller's queue) every ``team_change`` steps of the learning brain. A
  *brain* is a behavior name without its team: SoccerTwos' two teams share one brain (one
  network, trained on whichever team learns); StrikersVsGoalie's Striker and Goalie are
  two brains, each learning when its team does.
- **Snapshots**: every ``save_steps`` trainer steps the learning policy is copied into a
  ring of ``window`` snapshots, with its ELO. Every ``swap_steps`` steps of the other
  teams (ghost steps), and at each team change, those teams get a new opponent: a random
  snapshot, or with probability ``play_against_latest_model_ratio`` the current policy
  (copied then, fixed until the next swap).
- **Versions**: each team change or swap is a new weights version, and the learner keeps
  which team learned from which version on. A step counts as the learning team's only if
  the weights that acted were the learning policy's: whatever the lag of a worker, or
  when it joined, its steps are classified by the version it acted with. An opponent
  travels as a ``Snapshot`` under a key of its own: a worker fetches it once, not with
  every version of the learning policy.
- **ELO**: from the learning team's agents whose episode ended with their whole group,
  not interrupted, on any worker: the last step's reward plus group reward gives a win
  (> 0), a loss (< 0) or a draw; the current ELO moves by ``result - expected`` and the
  opponent's snapshot by the opposite (ML-Agents' formula, no K factor).
"""

from __future__ import annotations

import re
import uuid
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from batches import keys
from batches.contracts import Snapshot
from batches.specs import spec_from_dict

if TYPE_CHECKING:
    from tensordict import TensorDict

    from learners.trainer_config.settings import SelfPlaySettings

TEAM = re.compile(r"\?team=(\d+)")
State = dict[str, np.ndarray]


def team_of(behavior: str) -> int:
    match = TEAM.search(behavior)
    return int(match.group(1)) if match else 0


@dataclass
class Ghost:
    """One brain's snapshots, ELOs and counters (ML-Agents' ``GhostTrainer``)."""

    settings: SelfPlaySettings
    opponent_state: State  # what the brain's teams that do not learn act with
    opponent_key: str = ""  # names that state for good (workers load it once)
    snapshots: list[State] = field(default_factory=list)
    snapshot_keys: list[str] = field(default_factory=list)
    elos: list[float] = field(default_factory=list)  # window + 1; the last: the learning one
    slot: int = 0  # the ring's next slot
    opponent: int = -1  # the snapshot the other teams play (-1: a copy of the current)
    learning_team: int = -1  # the controller's team at this ghost's last swap
    last_save: int = 0
    last_swap: int = 0
    last_team_change: int = 0
    ghost_steps: int = 0  # steps of this brain's teams while they did not learn

    @property
    def elo(self) -> float:
        return self.elos[-1]

    def save(self, current: State) -> None:
        key = uuid.uuid4().hex  # unique across learner restarts: workers cache by it
        if self.slot < len(self.snapshots):
            self.snapshots[self.slot], self.snapshot_keys[self.slot] = current, key
        else:
            self.snapshots.append(current)
            self.snapshot_keys.append(key)
        self.elos[self.slot] = self.elo
        self.slot = (self.slot + 1) % self.settings.window

    def swap(self, current: State, rng: np.random.Generator) -> None:
        if rng.uniform() < 1 - self.settings.play_against_latest_model_ratio:
            self.opponent = int(rng.integers(len(self.snapshots)))
            self.opponent_state = self.snapshots[self.opponent]
            self.opponent_key = self.snapshot_keys[self.opponent]
        else:
            self.opponent, self.opponent_state = -1, current
            self.opponent_key = uuid.uuid4().hex


def _first_ghost(settings: SelfPlaySettings, current: State) -> Ghost:
    """A brain's ghost before any update: ``current`` its first snapshot and opponent."""
    ghost = Ghost(settings, current, elos=[settings.initial_elo] * (settings.window + 1))
    ghost.save(current)
    ghost.opponent_key = ghost.snapshot_keys[0]
    return ghost


class SelfPlay:
    """The ghost controller and the brains' ghosts of one run."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.learning_team = -1
        self.queue: deque[int] = deque()
        self.ghosts: dict[str, Ghost] = {}  # brain -> its ghost
        self.team_ghost: dict[int, str] = {}  # team -> the brain playing it
        self.changes: list[tuple[int, int]] = []  # (first version, learning team), ascending

    def join(self, brain: str, team: int, settings: SelfPlaySettings, current: State) -> None:
        """A behavior id seen for the first time: its brain's ghost (the initial policy as
        the first snapshot and opponent) and its team in the controller's queue."""
        if brain not in self.ghosts:
            self.ghosts[brain] = _first_ghost(settings, current)
        if team not in self.team_ghost:
            self.team_ghost[team] = brain
            if self.learning_team < 0:
                self.learning_team = team
                self.changes.append((0, team))
            else:
                self.queue.append(team)
        ghost = self.ghosts[brain]
        if ghost.learning_team < 0:
            ghost.learning_team = self.learning_team

    def start_from(self, brain: str, current: State) -> None:
        """The brain's networks were loaded before it learned (``--initialize-from``): its
        ghost starts from them, as ML-Agents' takes its first snapshot after loading, and
        not from the factory's weights it joined with."""
        old = self.ghosts[brain]
        ghost = _first_ghost(old.settings, current)
        ghost.learning_team = old.learning_team
        self.ghosts[brain] = ghost

    def snapshot_keys(self) -> set[str]:
        """The keys of every state an opponent may act with (the windows, the opponents)."""
        return {k for g in self.ghosts.values() for k in (*g.snapshot_keys, g.opponent_key)}

    def learning(self, team: int, versions: torch.Tensor) -> torch.Tensor:
        """Per step: whether ``team`` learned at the version that acted."""
        starts = torch.tensor([v for v, _ in self.changes], dtype=torch.int64)
        teams = torch.tensor([t for _, t in self.changes], dtype=torch.int64)
        at = torch.searchsorted(starts, versions.cpu().contiguous(), right=True) - 1
        return (teams[at.clamp(min=0)] == team).to(versions.device)

    def weights_of(self, brain: str, team: int, current: State) -> State | Snapshot:
        """The learning team acts with ``current``; the others with their opponent, a
        :class:`Snapshot` that each worker loads once."""
        if team == self.learning_team:
            return current
        ghost = self.ghosts[brain]
        return Snapshot(ghost.opponent_key, ghost.opponent_state)

    def record_games(self, brain: str, segment: TensorDict, learning: torch.Tensor) -> None:
        """ELO from the learning team's agents whose game ended (with their group, not
        interrupted) in ``segment``."""
        nxt = segment[keys.NEXT]
        ended = nxt[keys.TERMINATED].reshape(-1) & learning
        mates = segment.get(keys.GROUPMATES, None)
        if mates is not None and mates[keys.PRESENT].shape[1]:
            ended &= ~(mates[keys.PRESENT] & ~mates[keys.DONE]).any(-1)
        final = (nxt[keys.REWARD] + nxt[keys.GROUP_REWARD]).reshape(-1)[ended]
        ghost = self.ghosts[brain]
        for reward in final.tolist():
            result = 1.0 if reward > 0 else 0.0 if reward < 0 else 0.5
            change = self._elo_change(ghost.elo, result)
            ghost.elos[-1] += change

    def _elo_change(self, rating: float, result: float) -> float:
        """ML-Agents' ``compute_elo_rating_changes``: against the opponent's snapshot."""
        opponents = [self.ghosts[b] for t, b in self.team_ghost.items() if t != self.learning_team]
        opponent_rating = opponents[-1].elos[opponents[-1].opponent] if opponents else 0.0
        mine, theirs = 10 ** (rating / 400), 10 ** (opponent_rating / 400)
        change = result - mine / (mine + theirs)
        for ghost in opponents:
            ghost.elos[ghost.opponent] -= change
        return change

    def advance(
        self,
        brain: str,
        steps: int,
        version: int,
        current: Callable[[], State],
        finished: bool = False,
    ) -> bool:
        """After the brain's steps grew (``steps``: its learning steps), as its ghost trainer
        does: the team change, a snapshot, a swap of the opponent. True when what a team
        acts with changed: ``version`` is then the new weights version.

        ``finished``: the brain has its ``max_steps``. Unlike mlagents-learn, whose run then
        waits forever on a side that never got its turn (its warning when ``team_change``
        exceeds ``max_steps``), the next team takes over at once."""
        ghost = self.ghosts[brain]
        s, changed = ghost.settings, False
        handover = (
            finished
            and self.team_ghost.get(self.learning_team) == brain
            and bool(self.queue)
            and self.team_ghost[self.queue[0]] != brain
        )
        if (steps - ghost.last_team_change > s.team_change or handover) and self.queue:
            self.queue.append(self.learning_team)
            self.learning_team = self.queue.popleft()
            self.changes.append((version, self.learning_team))
            ghost.last_team_change, changed = steps, True
        if steps - ghost.last_save > s.save_steps:
            ghost.save(current())
            ghost.last_save = steps
        if (
            ghost.learning_team != self.learning_team
            or ghost.ghost_steps - ghost.last_swap > s.swap_steps
        ):
            ghost.learning_team = self.learning_team
            ghost.swap(current(), self.rng)
            ghost.last_swap, changed = ghost.ghost_steps, True
        return changed

    # --- checkpoints --------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Plain containers and tensors: a checkpoint loads with ``weights_only``."""

        def tensors(state: State) -> dict[str, torch.Tensor]:
            return {k: torch.from_numpy(v) for k, v in state.items()}

        ghosts = {}
        for brain, g in self.ghosts.items():
            fields = {k: v for k, v in vars(g).items() if k != "settings"}
            fields["opponent_state"] = tensors(g.opponent_state)
            fields["snapshots"] = [tensors(s) for s in g.snapshots]
            ghosts[brain] = fields
        return {
            "learning_team": self.learning_team,
            "queue": list(self.queue),
            "team_ghost": dict(self.team_ghost),
            "changes": [list(c) for c in self.changes],
            "rng": self.rng.bit_generator.state,
            "ghosts": ghosts,
        }

    def load_state_dict(self, state: dict[str, Any], settings: dict[str, Any]) -> None:
        """``settings``: each brain's ``SelfPlaySettings`` (from the config)."""

        def arrays(tensors: dict[str, torch.Tensor]) -> State:
            return {k: v.numpy() for k, v in tensors.items()}

        self.learning_team = int(state["learning_team"])
        self.queue = deque(int(t) for t in state["queue"])
        self.team_ghost = {int(t): b for t, b in state["team_ghost"].items()}
        self.changes = [(int(v), int(t)) for v, t in state["changes"]]
        self.rng.bit_generator.state = state["rng"]
        self.ghosts = {}
        for brain, fields in state["ghosts"].items():
            fields = dict(fields)
            fields["opponent_state"] = arrays(fields["opponent_state"])
            fields["snapshots"] = [arrays(s) for s in fields["snapshots"]]
            self.ghosts[brain] = Ghost(settings=settings[brain], **fields)


def learning_steps(segment: TensorDict, keep: torch.Tensor) -> TensorDict:
    """The steps the learning policy acted, as trajectories: where a kept step's successor
    in its trajectory is not kept (the team stopped learning mid-game), the kept part ends
    there, truncated, bootstrapping from that step's next observation."""
    if bool(keep.all()):
        return segment
    done = segment[keys.NEXT, keys.DONE].reshape(-1)
    followed_by_dropped = torch.zeros_like(keep)
    followed_by_dropped[:-1] = ~keep[1:]
    cut = keep & ~done & followed_by_dropped
    part = segment[keep]
    if bool(cut.any()):
        rows = cut[keep]
        part[keys.NEXT, keys.DONE][rows] = True
        part[keys.NEXT, keys.TRUNCATED][rows] = True
        if (cuts := part.get((keys.NEXT, keys.CUT), None)) is not None:
            cuts[rows] = True
    return part


def as_brain(segment: TensorDict, sensors: list[str]) -> TensorDict:
    """A team's steps under its brain's sensor names, by position: SoccerTwos' teams name
    their ray sensors after their colour, and share one network."""
    own = [o.name for o in spec_from_dict(segment.get_non_tensor(keys.SPEC)).observation_specs]
    if own == sensors:
        return segment
    if len(own) != len(sensors):
        raise ValueError(
            f"{segment.get_non_tensor(keys.BEHAVIOR)}: {len(own)} sensors, its brain's "
            f"network has {len(sensors)}: the teams of a self-play behavior must observe alike"
        )
    segment = segment.clone(recurse=False)  # the structure only: the tensors are shared
    present = set(segment.keys(True))
    for place in (
        (keys.OBS,),
        (keys.NEXT, keys.OBS),
        (keys.GROUPMATES, keys.OBS),
        (keys.NEXT, keys.GROUPMATES, keys.OBS),
    ):
        values = {n: segment.get((*place, n)) for n in own if (*place, n) in present}
        for name in values:
            del segment[(*place, name)]
        for name, new in zip(own, sensors, strict=True):
            if name in values:
                segment.set((*place, new), values[name])
    return segment
