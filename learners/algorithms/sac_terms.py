"""The pieces of SAC's losses over Q outputs (``learners/algorithms/sac.py``), with discrete
branches condensed as ML-Agents condenses them: each branch's masked log-probabilities, the Q of the
taken actions, the next state's soft value; and the allowed-mask of each step's next state. Q
outputs are ``[..., streams, outputs]``: one set per reward stream (the extrinsic signal's, then
each other signal's, as ML-Agents' Q networks have a head per reward signal)."""

from __future__ import annotations

import torch

# replay buffer: the continuous action (float [c]) and the discrete indices (int64 [k])
CONTINUOUS_ACTION, DISCRETE_ACTION = "continuous_action", "discrete_action"
MASKED_LOGIT = -1e8  # finite, so p * log p is 0 (not nan) for masked actions
TINY_PROBABILITY = 1e-8  # log p of a masked action in the target (its weight p is 0)


def masked_logits(logits: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Masked actions (mask False) get a finite logit of probability exactly 0."""
    return logits if mask is None else logits.masked_fill(~mask, MASKED_LOGIT)


def split(values: torch.Tensor, branches: tuple[int, ...]) -> tuple[torch.Tensor, ...]:
    """Q outputs (or logits, or masks) -> one tensor per branch."""
    return torch.split(values, branches, dim=-1)


def log_probs(
    logits: torch.Tensor, mask: torch.Tensor, branches: tuple[int, ...]
) -> list[torch.Tensor]:
    """Each branch's masked log-softmax (masked actions: probability exactly 0)."""
    pairs = zip(split(logits, branches), split(mask, branches), strict=True)
    return [torch.log_softmax(masked_logits(part, m), dim=-1) for part, m in pairs]


def taken(
    values: torch.Tensor, actions: torch.Tensor | None, branches: tuple[int, ...]
) -> torch.Tensor:
    """Q of the stored actions ``[2, B, streams]``: the mean over branches of each
    branch's value of its action (ML-Agents' condensed Q); continuous only: the output."""
    if not branches:
        return values.squeeze(-1)
    assert actions is not None
    q, b, streams = values.shape[:3]
    chosen = [
        part.gather(-1, actions[:, i].view(1, b, 1, 1).expand(q, b, streams, 1)).squeeze(-1)
        for i, part in enumerate(split(values, branches))
    ]
    return torch.stack(chosen).mean(0)


def expected_value(
    logits: torch.Tensor,
    mask: torch.Tensor,
    values: torch.Tensor,
    alpha: torch.Tensor,
    branches: tuple[int, ...],
) -> torch.Tensor:
    """The soft value ``[B, streams]`` of each branch's masked softmax over ``values``
    ``[B, streams, outputs]`` (``alpha``: one per branch), the mean over branches."""
    per_branch = []
    parts = zip(*(split(x, branches) for x in (logits, values, mask)), strict=True)
    for i, (branch_logits, value, allowed) in enumerate(parts):
        prob = torch.softmax(masked_logits(branch_logits, allowed), dim=-1).unsqueeze(-2)
        log = torch.where(prob == 0, TINY_PROBABILITY, prob).log()
        per_branch.append((prob * (value - alpha[i] * log)).sum(-1))
    return torch.stack(per_branch).mean(0)


def next_mask(mask: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
    """The allowed-mask of each step's next state: the next step's own mask when it is in
    the same trajectory (packed trajectories end with ``done``); otherwise (episode end,
    horizon cut) all allowed, as no mask was observed for that state."""
    result = torch.ones_like(mask)
    follows = ~done[:-1, 0]
    result[:-1] = torch.where(follows.unsqueeze(-1), mask[1:], True)
    return result
