"""Reward terms and the convergence measure (paper eq. 9; reference README).

    phi = sqrt(|u|^2 + |v|^2)
    E   = sqrt(trapezoid(phi^2, t))
    s   = |fft(phi)|                      (fftshift does not change the moments)
    M4  = mean((s - mean s)^4) / std(s)^4  (population std)
    r   = E / M4
"""
from __future__ import annotations

import torch

from laserrl.physics.checks import check_fields
from laserrl.physics.params import CavityParams

__all__ = ["amplitude", "kurtosis", "reward_terms", "convergence", "trapezoid_energy"]


def trapezoid_energy(power: torch.Tensor, dt: float) -> torch.Tensor:
    """Trapezoid rule over the last axis of the n samples (not a periodic sum)."""
    return dt * (power.sum(-1) - 0.5 * (power[..., 0] + power[..., -1]))


def amplitude(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """phi = sqrt(|u|^2 + |v|^2), real (B, n)."""
    return torch.sqrt(u.real.square() + u.imag.square() + v.real.square() + v.imag.square())


def reward_terms(u: torch.Tensor, v: torch.Tensor, params: CavityParams):
    """(E, M4, r) of a batch of field pairs, each (B,) real.

    A field of zero spectrum spread (std s = 0, e.g. all zeros) has undefined
    kurtosis; it is given M4 = inf, hence r = 0.
    """
    check_fields(u, v, params)
    phi = amplitude(u, v)
    energy = torch.sqrt(trapezoid_energy(phi.square(), params.dt).clamp_min(0.0))
    m4 = kurtosis(torch.fft.fft(phi).abs())
    return energy, m4, energy / m4


def kurtosis(s: torch.Tensor) -> torch.Tensor:
    """M4 = mean((s - mean s)^4) / std(s)^4 over the last axis (population std); inf where s has
    no spread."""
    centred = s - s.mean(-1, keepdim=True)
    var = centred.square().mean(-1)
    m4 = centred.pow(4).mean(-1) / var.square()
    return torch.where(var > 0, m4, torch.full_like(m4, float("inf")))


def convergence(u: torch.Tensor, v: torch.Tensor, u_prev: torch.Tensor, v_prev: torch.Tensor) -> torch.Tensor:
    """norm(phi_j - phi_{j-1}) / norm(phi_{j-1}) per cavity, (B,)."""
    phi, phi_prev = amplitude(u, v), amplitude(u_prev, v_prev)
    return torch.linalg.vector_norm(phi - phi_prev, dim=-1) / torch.linalg.vector_norm(phi_prev, dim=-1).clamp_min(
        torch.finfo(phi.dtype).tiny
    )
