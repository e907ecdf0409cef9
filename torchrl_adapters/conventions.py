"""Our segments under torchrl's key names, so that torchrl's losses, value estimators and
replay buffers read them with their defaults: ``observation`` (the sensor's tensor, or a
TensorDict of sensors by name when a behavior has several), ``action`` (the continuous or
discrete tensor, or both by name for a hybrid action), ``action_log_prob`` (the action's
log-probability: the sum of its components'), and under ``next``: ``observation``,
``reward``, ``done``, ``terminated``, ``truncated`` (``[N, 1]``). Beside them:
``agent_id``, ``team`` (of a ``?team=N`` behavior id), ``group_id``, ``policy_version``,
``worker``, ``action_mask`` (discrete), ``("next", "group_reward")``, and the behavior's
name as a non-tensor ``behavior``.

Rows stay in order, each one agent's consecutive steps ending with ``done`` (an episode's
end, or ``truncated`` at a horizon cut): a flat batch is what torchrl's GAE takes, its
trajectories separated by those flags.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from batches import keys

if TYPE_CHECKING:
    import torch
    from tensordict import TensorDict

OBSERVATION = "observation"
ACTION = "action"
LOG_PROB = "action_log_prob"  # torchrl's losses' default (tensordict's composite_lp_aggregate off)
LEGACY_LOG_PROB = "sample_log_prob"  # what modules built with the aggregate on write
BEHAVIOR = "behavior"
TEAM = "team"


def team_of(behavior: str) -> int:
    """``SoccerTwos?team=1`` -> 1 (0 without a team)."""
    _, _, query = behavior.partition("?team=")
    return int(query) if query.isdigit() else 0


def observation(sensors: TensorDict) -> torch.Tensor | TensorDict:
    """One sensor: its tensor; several: the TensorDict of them by name."""
    names = list(sensors.keys())
    return sensors[names[0]] if len(names) == 1 else sensors


def action(actions: TensorDict, continuous: int, branches: int) -> torch.Tensor | TensorDict:
    """The continuous or the discrete part, whichever the behavior has; both: by name."""
    if continuous and branches:
        return actions
    return actions[keys.CONTINUOUS] if continuous else actions[keys.DISCRETE]


def to_torchrl(segment: TensorDict) -> TensorDict:
    """A segment (``docs/batch-format.md``) as torchrl names it."""
    import torch
    from tensordict import TensorDict

    behavior = segment.get_non_tensor(keys.BEHAVIOR)
    spec = segment.get_non_tensor(keys.SPEC)
    continuous, branches = int(spec["continuous"]), len(spec["discrete"])
    nxt = segment[keys.NEXT]
    out = TensorDict(
        {
            OBSERVATION: observation(segment[keys.OBS]),
            ACTION: action(segment[keys.ACTION], continuous, branches),
            LOG_PROB: segment[keys.LOG_PROB].sum(-1),
            keys.AGENT_ID: segment[keys.AGENT_ID],
            TEAM: torch.full_like(segment[keys.AGENT_ID], team_of(behavior)),
            keys.GROUP_ID: segment[keys.GROUP_ID],
            keys.POLICY_VERSION: segment[keys.POLICY_VERSION],
            keys.NEXT: {
                OBSERVATION: observation(nxt[keys.OBS]),
                keys.REWARD: nxt[keys.REWARD],
                keys.GROUP_REWARD: nxt[keys.GROUP_REWARD],
                keys.DONE: nxt[keys.DONE],
                keys.TERMINATED: nxt[keys.TERMINATED],
                keys.TRUNCATED: nxt[keys.TRUNCATED],
            },
        },
        batch_size=segment.batch_size,
    )
    for key in (keys.ACTION_MASK, keys.WORKER):  # discrete behaviors; workers' segments
        if key in segment:
            out[key] = segment[key]
    out.set_non_tensor(BEHAVIOR, behavior)
    return out
