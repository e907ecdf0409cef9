"""The groupmates a worker records with each step, against the trajectories mlagents-learn
1.1.0's own ``AgentProcessor`` makes of the same steps (what POCA's critic reads).

``check_trajectories_vs_mlagents.py`` checks the rows of agents without groups. This one
sends a stream of agents in groups of three, as DungeonEscape's rooms send them, through
our ``rollout.collecting.segments.SegmentBuilder`` and ML-Agents' agent processor, with the same
action for each decision: members that skip an exchange (their status persists), a member
sacrificed mid-episode (it reports once more, ``done``, and is gone until its group
restarts it with a new id), groups that end together (escaped, with a group reward, or
interrupted at their max step) and start again in the same exchange or later, group
rewards mid-episode too, rows cut at ``time_horizon``. Every observation is numbered.
Both sides must give the same trajectories, step by step: each step's groupmates (the
observation each acted on, its action, its latest reward and ``done``), its group reward,
and the groupmates' observations after the trajectory's last step.

    .venv/bin/python -m benchmarks.equality.check_groups_vs_mlagents --seeds 0 1 2
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.equality.check_trajectories_vs_mlagents import (
    BRANCH,
    mlagents_agreement,
    our_segments,
    unity_steps,
)
from benchmarks.equality.common import run_sides

GROUPS, SIZE, EXCHANGES, HORIZON = 2, 3, 300, 6
Mates = tuple[tuple[int, float, int, bool], ...]  # (observation number, reward, action, done)
# a trajectory: per step (observation number, action, reward, group reward, groupmates),
# whether it ends its episode (terminated), the next observation's number, the groupmates'
Step = tuple[int, int, float, float, Mates]
Trajectory = tuple[tuple[Step, ...], bool, int, tuple[int, ...]]


def stream(seed: int) -> list[dict[str, np.ndarray]]:
    """Exchanges of ``GROUPS`` groups of ``SIZE``: observations ``[agent, number]``
    numbered in the order sent, group ids, group rewards; per exchange the decision
    agents' actions and log-probabilities."""
    rng = np.random.default_rng(seed)
    ids = np.arange(GROUPS * SIZE).reshape(GROUPS, SIZE)  # each place's agent now
    alive = np.ones((GROUPS, SIZE), bool)
    away = np.zeros(GROUPS, np.int64)  # exchanges until an ended group starts again
    next_id, number, exchanges = GROUPS * SIZE, 0, []
    for _ in range(EXCHANGES):
        dec: list[tuple[int, int, int, float, float]] = []  # agent, number, group, rewards
        term: list[tuple[int, int, int, float, float, bool]] = []  # ... interrupted
        for g in range(GROUPS):
            if away[g] > 0:
                away[g] -= 1
                if away[g] == 0:  # the group starts again: its first decisions
                    for place in range(SIZE):
                        number += 1
                        dec.append((int(ids[g, place]), number, g + 1, 0.0, 0.0))
                continue
            ends = rng.random() < 0.05
            escaped = ends and rng.random() < 0.5
            bonus = 1.0 if escaped else float(rng.random() < 0.05) * 0.5  # mid-episode too
            for place in range(SIZE):
                if not alive[g, place]:
                    continue
                agent, reward = int(ids[g, place]), float(rng.normal(0.0, 0.1))
                if ends:  # every member left ends with the group
                    number += 1
                    term.append((agent, number, g + 1, reward, bonus, not escaped))
                    continue
                draw = rng.random()
                if draw < 0.04 and alive[g].sum() > 1:  # sacrificed: it reports once more
                    number += 1
                    term.append((agent, number, g + 1, reward, bonus, False))
                    alive[g, place] = False
                elif draw < 0.14:
                    continue  # no report this exchange (its status persists)
                else:
                    number += 1
                    dec.append((agent, number, g + 1, reward, bonus))
            if ends:  # the sacrificed come back with new ids; the group starts again
                for place in range(SIZE):
                    if not alive[g, place]:
                        ids[g, place], next_id = next_id, next_id + 1
                alive[g] = True
                if rng.random() < 0.6:
                    for place in range(SIZE):
                        number += 1
                        dec.append((int(ids[g, place]), number, g + 1, 0.0, 0.0))
                else:
                    away[g] = int(rng.integers(1, 4))
        exchanges.append(
            {
                "dec": np.array([(a, n) for a, n, *_ in dec], np.int64).reshape(-1, 2),
                "dec_group": np.array([g for _, _, g, _, _ in dec], np.int32),
                "dec_reward": np.array([r for *_, r, _ in dec], np.float32),
                "dec_group_reward": np.array([b for *_, b in dec], np.float32),
                "term": np.array([(a, n) for a, n, *_ in term], np.int64).reshape(-1, 2),
                "term_group": np.array([g for _, _, g, *_ in term], np.int32),
                "term_reward": np.array([t[3] for t in term], np.float32),
                "term_group_reward": np.array([t[4] for t in term], np.float32),
                "interrupted": np.array([t[5] for t in term], bool),
                "action": rng.integers(0, BRANCH, (len(dec), 1)),
                "log_prob": rng.normal(size=(len(dec), 1)).astype(np.float32),
            }
        )
    return exchanges


def grouped_steps(exchange: dict[str, np.ndarray]) -> tuple[Any, Any]:
    """The exchange as ``mlagents_envs`` hands it over, with group ids and rewards."""
    from mlagents_envs.base_env import DecisionSteps, TerminalSteps

    decisions, terminals = unity_steps(exchange)
    return (
        DecisionSteps(
            decisions.obs,
            decisions.reward,
            decisions.agent_id,
            None,
            exchange["dec_group"],
            exchange["dec_group_reward"],
        ),
        TerminalSteps(
            terminals.obs,
            terminals.reward,
            terminals.interrupted,
            terminals.agent_id,
            exchange["term_group"],
            exchange["term_group_reward"],
        ),
    )


def ours(seed: int, out: Path) -> None:
    from batches import keys

    exchanges = stream(seed)
    rows: list[Trajectory] = []
    for data in our_segments(exchanges, grouped_steps, HORIZON):
        mates, after = data[keys.GROUPMATES], data[keys.NEXT][keys.GROUPMATES]
        ends = np.flatnonzero(data[keys.NEXT][keys.DONE][:, 0]) + 1
        for start, stop in zip([0, *ends[:-1]], ends, strict=True):
            steps = []
            for t in range(start, stop):
                present = np.flatnonzero(mates[keys.PRESENT][t])
                status = (
                    (
                        int(mates[keys.OBS]["v"][t, m, 1]),
                        float(mates[keys.REWARD][t, m]),
                        int(mates[keys.ACTION][keys.DISCRETE][t, m, 0]),
                        bool(mates[keys.DONE][t, m]),
                    )
                    for m in present
                )
                steps.append(
                    (
                        int(data[keys.OBS]["v"][t, 1]),
                        int(data[keys.ACTION][keys.DISCRETE][t, 0]),
                        float(data[keys.NEXT][keys.REWARD][t, 0]),
                        float(data[keys.NEXT][keys.GROUP_REWARD][t, 0]),
                        tuple(sorted(status)),
                    )
                )
            last = stop - 1
            present = np.flatnonzero(mates[keys.PRESENT][last])
            rows.append(
                (
                    tuple(steps),
                    bool(data[keys.NEXT][keys.TERMINATED][last, 0]),
                    int(data[keys.NEXT][keys.OBS]["v"][last, 1]),
                    tuple(sorted(int(after[keys.OBS]["v"][last, m, 1]) for m in present)),
                )
            )
    out.write_bytes(pickle.dumps({"exchanges": exchanges, "rows": rows}))


def described(trajectory: Any) -> Trajectory:
    """One of ML-Agents' trajectories as ``ours`` writes a row, groupmates included."""
    steps = tuple(
        (
            int(s.obs[0][1]),
            int(s.action.discrete[0]),
            float(s.reward),
            float(s.group_reward),
            tuple(
                sorted(
                    (int(m.obs[0][1]), float(m.reward), int(m.action.discrete[0]), m.done)
                    for m in s.group_status
                )
            ),
        )
        for s in trajectory.steps
    )
    last = trajectory.steps[-1]
    return (
        steps,
        bool(last.done and not last.interrupted),
        int(trajectory.next_obs[0][1]),
        tuple(sorted(int(o[0][1]) for o in trajectory.next_group_obs)),
    )


def mlagents(case: Path, anchor: Path) -> float:
    """ML-Agents' agent processor on the case's stream; returns 0 when its trajectories
    are ours, else the share of trajectories that differ."""
    return mlagents_agreement(case, anchor, grouped_steps, HORIZON, described)


if __name__ == "__main__":
    run_sides(__spec__.name, ours, mlagents, __doc__)
