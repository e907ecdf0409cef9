"""The rows a worker cuts from Unity's steps, against the trajectories mlagents-learn
1.1.0's own ``AgentProcessor`` makes of the same steps.

The exact checks of the updates (``check_ppo_vs_mlagents.py`` ...) start from a buffer;
this one checks what goes into it. One scripted stream of exchanges, as a build sends
them (``DecisionSteps`` and ``TerminalSteps``), goes through our
``rollout.collecting.segments.SegmentBuilder`` and through ML-Agents' agent processor, with the same
action chosen for each decision. The stream has what real builds do: agents that skip
exchanges (decision periods), episodes that end and start again in the same exchange or
some exchanges later, episodes interrupted at their max step, rewards on every step,
rows cut at ``time_horizon``. Every observation is numbered, so each step is known by
its number. Both sides must give the same trajectories: the same steps in the same
order, each with its action, log-probability and reward, the same ends (terminated or
not) and the same observation after each trajectory's last step.

    .venv/bin/python -m benchmarks.equality.check_trajectories_vs_mlagents --seeds 0 1 2
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.equality.common import anchor_workarounds, run_sides, vector_spec

AGENTS, EXCHANGES, HORIZON, BRANCH = 6, 400, 5, 3
# a trajectory: observation numbers, actions, log-probabilities, rewards, whether it ends
# its episode (terminated, not interrupted), the number of the observation after it
Numbers = tuple[int, ...]
Trajectory = tuple[Numbers, Numbers, tuple[float, ...], tuple[float, ...], bool, int]


def stream(seed: int) -> list[dict[str, np.ndarray]]:
    """Exchanges of ``AGENTS`` agents: each observation ``[agent, number]``, numbered in
    the order sent; per exchange the decision agents' actions and log-probabilities."""
    rng = np.random.default_rng(seed)
    away = np.zeros(AGENTS, np.int64)  # exchanges until an ended agent's next episode
    number = 0
    exchanges = []
    for _ in range(EXCHANGES):
        dec: list[tuple[int, int, float]] = []  # (agent, observation number, reward)
        term: list[tuple[int, int, float, bool]] = []  # ... interrupted
        for agent in range(AGENTS):
            if away[agent] > 0:
                away[agent] -= 1
                if away[agent] == 0:  # a new episode: its first decision, no reward yet
                    number += 1
                    dec.append((agent, number, 0.0))
                continue
            draw = rng.random()
            if draw < 0.1:  # the episode ends (at its max step in a third of cases)
                number += 1
                term.append((agent, number, float(rng.normal()), bool(rng.random() < 0.3)))
                if rng.random() < 0.6:  # and the next starts in the same exchange
                    number += 1
                    dec.append((agent, number, 0.0))
                else:
                    away[agent] = int(rng.integers(1, 4))
            elif draw < 0.25:
                continue  # no decision this exchange (a longer decision period)
            else:
                number += 1
                dec.append((agent, number, float(rng.normal())))
        exchanges.append(
            {
                "dec": np.array([(a, n) for a, n, _ in dec], np.int64).reshape(-1, 2),
                "dec_reward": np.array([r for _, _, r in dec], np.float32),
                "term": np.array([(a, n) for a, n, _, _ in term], np.int64).reshape(-1, 2),
                "term_reward": np.array([r for _, _, r, _ in term], np.float32),
                "interrupted": np.array([i for *_, i in term], bool),
                "action": rng.integers(0, BRANCH, (len(dec), 1)),
                "log_prob": rng.normal(size=(len(dec), 1)).astype(np.float32),
            }
        )
    return exchanges


def unity_steps(exchange: dict[str, np.ndarray]) -> tuple[Any, Any]:
    """The exchange as ``mlagents_envs`` hands it over: (DecisionSteps, TerminalSteps)."""
    from mlagents_envs.base_env import DecisionSteps, TerminalSteps

    dec, term = exchange["dec"], exchange["term"]
    zeros_d, zeros_t = np.zeros(len(dec), np.int32), np.zeros(len(term), np.int32)
    decisions = DecisionSteps(
        [dec.astype(np.float32)],
        exchange["dec_reward"],
        dec[:, 0].astype(np.int32),
        None,
        zeros_d,
        zeros_d.astype(np.float32),
    )
    terminals = TerminalSteps(
        [term.astype(np.float32)],
        exchange["term_reward"],
        exchange["interrupted"],
        term[:, 0].astype(np.int32),
        zeros_t,
        zeros_t.astype(np.float32),
    )
    return decisions, terminals


Steps = Callable[[dict[str, np.ndarray]], tuple[Any, Any]]  # an exchange's Unity steps


def our_segments(
    exchanges: list[dict[str, np.ndarray]], unity: Steps, horizon: int
) -> list[dict[str, Any]]:
    """The segments our ``SegmentBuilder`` packs from the exchanges (``unity``: each one's
    ``DecisionSteps`` and ``TerminalSteps``), acting as each exchange says."""
    from rollout.collecting.decisions import Decisions
    from rollout.collecting.segments import SegmentBuilder

    builder = SegmentBuilder("B?team=0", vector_spec(2, BRANCH), horizon)
    segments = []
    for exchange in exchanges:
        decisions, terminals = unity(exchange)
        builder.observe(decisions, terminals)
        if (segment := builder.collect()) is not None:
            segments.append(segment.data)
        chosen = Decisions(
            np.zeros((len(decisions), 0), np.float32), exchange["action"], exchange["log_prob"]
        )
        builder.act(decisions, chosen, 0)
    return segments


def ours(seed: int, out: Path) -> None:
    exchanges = stream(seed)
    rows: list[Trajectory] = []
    for data in our_segments(exchanges, unity_steps, HORIZON):
        ends = np.flatnonzero(data["next"]["done"][:, 0]) + 1
        for start, stop in zip([0, *ends[:-1]], ends, strict=True):
            piece = slice(start, stop)
            rows.append(
                (
                    tuple(int(n) for n in data["obs"]["v"][piece, 1]),
                    tuple(int(a) for a in data["action"]["discrete"][piece, 0]),
                    tuple(float(p) for p in data["sample_log_prob"][piece, 0]),
                    tuple(float(r) for r in data["next"]["reward"][piece, 0]),
                    bool(data["next"]["terminated"][stop - 1, 0]),
                    int(data["next"]["obs"]["v"][stop - 1, 1]),
                )
            )
    out.write_bytes(pickle.dumps({"exchanges": exchanges, "rows": rows}))


def mlagents_trajectories(
    exchanges: list[dict[str, np.ndarray]], unity: Steps, horizon: int
) -> list[Any]:
    """The trajectories ML-Agents' own agent processor makes of the exchanges, acting as
    each exchange says (its environment manager's step loop)."""
    from mlagents.trainers.action_info import ActionInfo
    from mlagents.trainers.agent_processor import AgentManagerQueue, AgentProcessor
    from mlagents.trainers.policy.torch_policy import TorchPolicy
    from mlagents.trainers.settings import NetworkSettings
    from mlagents.trainers.stats import StatsReporter
    from mlagents.trainers.torch_entities.action_log_probs import LogProbsTuple
    from mlagents.trainers.torch_entities.networks import SimpleActor
    from mlagents_envs.base_env import ActionTuple

    actor = {"conditional_sigma": False, "tanh_squash": False}
    policy = TorchPolicy(0, vector_spec(2, BRANCH), NetworkSettings(), SimpleActor, actor)
    processor = AgentProcessor(policy, "B?team=0", StatsReporter("check"), horizon)
    queue: AgentManagerQueue = AgentManagerQueue("B?team=0")
    processor.publish_trajectory_queue(queue)
    previous = ActionInfo.empty()
    for exchange in exchanges:
        decisions, terminals = unity(exchange)
        processor.add_experiences(decisions, terminals, 0, previous)
        action = ActionTuple(discrete=exchange["action"])
        outputs = {
            "action": action,
            "log_probs": LogProbsTuple(
                continuous=np.zeros((len(decisions), 0), np.float32),
                discrete=exchange["log_prob"],
            ),
        }
        previous = ActionInfo(action, action, outputs, list(decisions.agent_id))
    out = []
    while not queue.empty():
        out.append(queue.get_nowait())
    return out


def agreement(theirs: list[Any], mine: list[Any]) -> float:
    """0 when both sides' trajectories are the same (in any order), else the share that
    differ; prints the first differences."""
    mine, theirs = sorted(mine), sorted(theirs)
    count = sum(len(t[0]) for t in theirs)
    print(f"  ML-Agents: {len(theirs)} trajectories, {count} steps; ours: {len(mine)} rows")
    differ = [pair for pair in zip(theirs, mine, strict=False) if pair[0] != pair[1]]
    for their, our in differ[:3]:
        print(f"  differ:\n    ML   {their}\n    ours {our}")
    return 0.0 if theirs == mine else max(len(differ), 1) / max(len(theirs), 1)


def mlagents_agreement(
    case: Path, anchor: Path, unity: Steps, horizon: int, described: Callable[[Any], Any]
) -> float:
    """ML-Agents' agent processor on the case's stream, each trajectory ``described`` as
    ours wrote its rows; returns 0 when they are ours, else the share that differ."""
    anchor_workarounds(anchor)
    case_data = pickle.loads(case.read_bytes())
    trajectories = mlagents_trajectories(case_data["exchanges"], unity, horizon)
    return agreement([described(t) for t in trajectories], case_data["rows"])


def described(trajectory: Any) -> Trajectory:
    """One of ML-Agents' trajectories as ``ours`` writes a row."""
    steps, last = trajectory.steps, trajectory.steps[-1]
    return (
        tuple(int(s.obs[0][1]) for s in steps),
        tuple(int(s.action.discrete[0]) for s in steps),
        tuple(float(s.action_probs.discrete[0]) for s in steps),
        tuple(float(s.reward) for s in steps),
        bool(last.done and not last.interrupted),
        int(trajectory.next_obs[0][1]),
    )


def mlagents(case: Path, anchor: Path) -> float:
    """ML-Agents' agent processor on the case's stream; returns 0 when its trajectories
    are ours, else the share of trajectories that differ."""
    return mlagents_agreement(case, anchor, unity_steps, HORIZON, described)


if __name__ == "__main__":
    run_sides(__spec__.name, ours, mlagents, __doc__)
