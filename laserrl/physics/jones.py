"""Jones matrices of the waveplates and polarizer (paper eqs. 7-8).

    J_j = R(alpha_j) W_j R(-alpha_j),   R(a) = [[cos a, -sin a], [sin a, cos a]]
    W_quarter = diag(e^{-i pi/4}, e^{i pi/4})   (alpha1, alpha2)
    W_half    = diag(-i, i)                     (alpha3)
    W_pol     = diag(1, 0)                      (alpha_p)

Every J_j has period pi in alpha_j. The cavity applies J1 JP J2 J3 once per round trip.
"""
from __future__ import annotations

import math

import torch

QUARTER = (complex(math.cos(math.pi / 4), -math.sin(math.pi / 4)), complex(math.cos(math.pi / 4), math.sin(math.pi / 4)))
HALF = (-1j, 1j)
POLARIZER = (1.0 + 0j, 0j)


def element(alpha: torch.Tensor, eigen: tuple[complex, complex], dtype=torch.complex64) -> torch.Tensor:
    """R(alpha) diag(eigen) R(-alpha) for a batch of angles (radians): (..., 2, 2)."""
    c, s = torch.cos(alpha), torch.sin(alpha)
    a, b = eigen
    # R diag(a, b) R^T = [[a c^2 + b s^2, (a - b) c s], [(a - b) c s, a s^2 + b c^2]]
    cc, ss, cs = (c * c).to(dtype), (s * s).to(dtype), (c * s).to(dtype)
    m00 = a * cc + b * ss
    m01 = (a - b) * cs
    m11 = a * ss + b * cc
    return torch.stack([torch.stack([m00, m01], -1), torch.stack([m01, m11], -1)], -2)


def cavity_jones(angles: torch.Tensor, dtype=torch.complex64) -> torch.Tensor:
    """J1 @ JP @ J2 @ J3 for angles (..., 4) = (alpha1, alpha2, alpha3, alpha_p) in radians."""
    j1 = element(angles[..., 0], QUARTER, dtype)
    j2 = element(angles[..., 1], QUARTER, dtype)
    j3 = element(angles[..., 2], HALF, dtype)
    jp = element(angles[..., 3], POLARIZER, dtype)
    return j1 @ jp @ j2 @ j3


def apply_jones(m: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[u; v] <- M [u; v] pointwise in t, M of shape (B, 2, 2)."""
    # one batched matrix product rather than four complex products and two sums, each a
    # pass of its own in eager mode
    x = torch.matmul(m, torch.stack([u, v], -2))  # (B, 2, n)
    return x[..., 0, :], x[..., 1, :]
