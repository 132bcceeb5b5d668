"""Run a batch of cavities round trip by round trip until each converges."""
from __future__ import annotations

from dataclasses import dataclass

import warnings

import torch

from laserrl.physics.cavity import _round_trip
from laserrl.physics.checks import NonFiniteFieldError, as_batch, check_cavity, check_fields, check_finite
from laserrl.physics.observables import convergence
from laserrl.physics.params import CavityParams

__all__ = ["ConvergenceResult", "run_to_convergence", "NonFiniteFieldError", "check_finite", "CONVERGENCE_FLOOR", "effective_tolerance"]


#: Smallest convergence tolerance a dtype can resolve. In float32 the round-trip map
#: itself carries a roundoff floor in the change between round trips of a converged
#: state: about 6e-7 with the default split-step integrator and about 3e-6 with DOP853
#: (whose tableau coefficients up to ~40 amplify float32 rounding). complex64 runs use
#: max(tol, 1e-5), which holds for both with a margin; complex128 resolves the paper's 1e-6.
CONVERGENCE_FLOOR = {torch.complex64: 1e-5, torch.complex128: 0.0}


def effective_tolerance(tol: float, dtype: torch.dtype) -> float:
    """max(tol, CONVERGENCE_FLOOR[dtype]), warning once when the floor applies."""
    floor = CONVERGENCE_FLOOR.get(dtype, 0.0)
    if tol < floor:
        warnings.warn(
            f"convergence tolerance {tol:g} is below what {dtype} resolves; using {floor:g} "
            "(use complex128 fields for the paper's 1e-6)",
            stacklevel=3,
        )
        return floor
    return tol


@dataclass
class ConvergenceResult:
    u: torch.Tensor
    v: torch.Tensor
    round_trips: torch.Tensor  # (B,) int64: round trips each cavity used
    converged: torch.Tensor  # (B,) bool: change < tol reached within max_round_trips
    change: torch.Tensor  # (B,) last convergence measure
    tol: float  # tolerance used (see CONVERGENCE_FLOOR)


def run_to_convergence(u, v, angles, K, params: CavityParams, *, tol: float = 1e-6, max_round_trips: int = 500,
                       min_round_trips: int = 1, active: torch.Tensor | None = None,
                       compile: bool = False, cavity: torch.Tensor | None = None) -> ConvergenceResult:
    """Round trips until norm(phi_j - phi_{j-1}) / norm(phi_{j-1}) < tol, per cavity,
    but at least ``min_round_trips`` (1: the paper's rule, which may stop after the first).

    complex64 fields cannot resolve tolerances below 1e-5 (``CONVERGENCE_FLOOR``);
    a smaller ``tol`` is raised to that with a warning.

    Cavities that have converged (or are not in ``active``) are not integrated any
    further: each round trip runs only on the remaining subset. Checking the stop
    condition needs one host synchronisation per round trip.

    Args:
        u, v: (B, n) complex fields.  angles: (B, 4) radians.  K: (B,) or scalar.
        tol: convergence tolerance (paper: 1e-6).  max_round_trips: cap (paper: 500).
        min_round_trips: round trips before the stopping test may end a cavity's run.
        active: optional (B,) bool mask of cavities to run; others are returned unchanged.
        cavity: optional (B, 5) per-cavity D, E0, tau, g0, Gamma (``laserrl.physics.checks.check_cavity``).
    Returns:
        ConvergenceResult with the final fields and the round trips each cavity used.
    Raises:
        NonFiniteFieldError naming the cavities whose field became NaN or infinite.
    """
    check_fields(u, v, params)
    if not (tol >= 0):
        raise ValueError(f"tol must be >= 0, got {tol!r}")
    if int(max_round_trips) != max_round_trips or max_round_trips < 1:
        raise ValueError(f"max_round_trips must be a positive integer, got {max_round_trips!r}")
    if int(min_round_trips) != min_round_trips or not 1 <= min_round_trips <= max_round_trips:
        raise ValueError(f"min_round_trips must be an integer in [1, max_round_trips = {max_round_trips}], "
                         f"got {min_round_trips!r}")
    tol = effective_tolerance(tol, u.dtype)
    batch = u.shape[0]
    angles = as_batch(angles, batch, "angles", u, width=4)
    K = as_batch(K, batch, "K", u)
    cavity = check_cavity(cavity, batch, params)
    u, v = u.clone(), v.clone()
    count = torch.zeros(batch, dtype=torch.int64, device=u.device)
    change = torch.full((batch,), float("inf"), dtype=angles.dtype, device=u.device)
    running = torch.ones(batch, dtype=torch.bool, device=u.device) if active is None else active.clone().bool()
    converged = torch.zeros(batch, dtype=torch.bool, device=u.device)
    for _ in range(int(max_round_trips)):
        idx = running.nonzero().flatten()
        if idx.numel() == 0:
            break
        u_old, v_old = u[idx], v[idx]
        # inputs were checked above and every output is checked here, so the loop skips round_trip's own checks
        u_new, v_new = _round_trip(u_old, v_old, angles[idx], K[idx], params, compile, True,
                                   None if cavity is None else cavity[idx])
        check_finite(u_new, v_new, " during a round trip", index=idx)
        delta = convergence(u_new, v_new, u_old, v_old)
        u[idx], v[idx] = u_new, v_new
        count[idx] += 1
        change[idx] = delta
        done = (delta < tol) & (count[idx] >= min_round_trips)
        converged[idx] = done
        running[idx] = ~done
    return ConvergenceResult(u, v, count, converged, change, tol)
