"""Joint discrete actions over the controlled angles.

With m controlled angles there are 3^m joint actions. Action index a encodes one
digit per controlled angle, little-endian in base 3 (the first controlled angle is
the least significant digit): d_j = (a // 3^j) % 3, and the angle moves by
(d_j - 1) * step_j, i.e. digit 0 = decrease, 1 = hold, 2 = increase.
The all-hold action is (3^m - 1) / 2.
"""
from __future__ import annotations

import torch

__all__ = ["action_to_deltas", "deltas_to_action", "hold_action", "num_actions"]


def num_actions(m: int) -> int:
    return 3**m


def hold_action(m: int) -> int:
    return (3**m - 1) // 2


def action_to_deltas(action: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """(...,) integer actions -> (..., m) angle changes, with steps (m,) the step of each angle."""
    m = steps.shape[-1]
    powers = 3 ** torch.arange(m, device=action.device)
    digits = torch.div(action.long().unsqueeze(-1), powers, rounding_mode="floor") % 3
    return (digits - 1).to(steps.dtype) * steps


def deltas_to_action(signs: torch.Tensor) -> torch.Tensor:
    """(..., m) signs in {-1, 0, 1} -> (...,) action index (inverse of ``action_to_deltas``)."""
    m = signs.shape[-1]
    powers = 3 ** torch.arange(m, device=signs.device)
    return ((signs.long() + 1) * powers).sum(-1)
