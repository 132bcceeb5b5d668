"""Batched cavity round trip: propagate over z in [0, Z], then apply J1 JP J2 J3.

The propagation solves, in Fourier space (d_tt -> -k^2),

    i u_z + (D/2) u_tt - K u + (|u|^2 + A|v|^2) u + B v^2 u* = i R u
    i v_z + (D/2) v_tt + K v + (A|u|^2 + |v|^2) v + B u^2 v* = i R v
    R = g(E) (1 + tau d_tt) - Gamma,   g(E) = 2 g0 / (1 + E/E0),   E = trapezoid(|u|^2 + |v|^2, t)

with the fixed-step integrator that ``params.integrator`` names: "split"
(``laserrl.physics.split_step``) or "dop853" (``laserrl.physics.dop853``). Cavities whose
error estimate exceeds ``REFINE_ERROR`` are redone with 4x the steps; for "split" that
includes fields with power in modes its coarse pass does not resolve (white-noise starts).
The Jones matrices are those of ``laserrl.physics.jones``. Compilation is opt-in
(``compile=True``).
"""
from __future__ import annotations

import torch

from laserrl.physics.checks import _real_dtype, as_batch, check_cavity, check_fields
from laserrl.physics.dop853 import _STAGES, _stepper
from laserrl.physics.jones import apply_jones, cavity_jones
from laserrl.physics.params import CavityParams

__all__ = ["propagate", "round_trip", "fft_pairs_per_round_trip"]


def _propagate_fixed(u, v, K: torch.Tensor, params: CavityParams, compile: bool, cavity: torch.Tensor | None = None):
    """Fixed-step propagation; returns (u, v, error) with the integrator's error estimate."""
    step = _stepper(params, _real_dtype(u.dtype), u.device, bool(compile))
    w = torch.fft.fft(torch.stack([u, v], dim=-2))
    w, error = step(w, K) if cavity is None else step(w, K, cavity=cavity)
    x = torch.fft.ifft(w)
    return x[:, 0], x[:, 1], error


def fft_pairs_per_round_trip(params: CavityParams) -> int:
    """Inverse + forward FFT pairs of both fields that one round trip costs (no refinement):
    one per Strang step of the two passes (``params.split_passes``: 10 + 16 by default), or
    one per DOP853 stage."""
    return sum(params.split_passes) if params.integrator == "split" else _STAGES * params.z_steps


#: Error estimate above which a cavity's propagation is redone with finer steps, per
#: integrator. "split": |fine - coarse| / |fine| of the two Strang passes, 1e-4..6.3e-3
#: on the reference cases at the default 10 and 16 steps, whose extrapolated error is then
#: below 5e-5; 0.05 is 8x the largest of those, and the estimate is infinite for fields with
#: power in modes the coarse pass does not resolve (``split_step.UNRESOLVED_POWER``, the
#: first round trip from white noise). The estimate does not rank the extrapolated error
#: otherwise: their ratio varies 100-fold between states. "dop853": its embedded
#: step error estimate, 1e-6..1e-4 on ordinary states at 4 steps; an unstable step
#: (intense or fast-changing states) shows up orders of magnitude above that.
REFINE_ERROR = {"split": 0.05, "dop853": 1e-3}


def propagate(u: torch.Tensor, v: torch.Tensor, K, params: CavityParams, *, compile: bool = False,
              refine: bool = True, max_refinements: int = 3, cavity: torch.Tensor | None = None):
    """Propagate a batch of fields over z in [0, Z] (no Jones matrices).

    Args:
        u, v: (B, n) complex64 or complex128 fields.
        K: birefringence, a (B,) tensor or a scalar.
        params: cavity parameters; ``params.integrator`` and ``params.z_steps`` choose the
            fixed-step scheme (see ``CavityParams``).
        compile: fuse the step with ``torch.compile`` (a one-off compilation per process
            and batch-shape family, then faster steps).
        refine: redo cavities whose error estimate exceeds ``REFINE_ERROR`` (or
            that came out non-finite) with 4x finer steps, up to ``max_refinements`` times.
            Costs one host synchronisation.
        cavity: None (every cavity is ``params``'), or (B, 5) per-cavity values of D, E0, tau,
            g0, Gamma (``check_cavity``); needs ``integrator="split"``.
    Returns:
        (u, v) at z = Z.
    """
    check_fields(u, v, params)
    cavity = check_cavity(cavity, u.shape[0], params)
    return _propagate(u, v, as_batch(K, u.shape[0], "K", u), params, compile, refine, max_refinements, cavity)


def _propagate(u, v, K: torch.Tensor, params: CavityParams, compile: bool, refine: bool, max_refinements: int = 3,
               cavity: torch.Tensor | None = None):
    """``propagate`` of fields, (B,) K and per-cavity values that are already checked."""
    u_out, v_out, error = _propagate_fixed(u, v, K, params, compile, cavity)
    if not refine:
        return u_out, v_out
    for level in range(1, max_refinements + 1):
        bad = ~(error <= REFINE_ERROR[params.integrator])  # also catches NaN
        if not bool(bad.any()):
            break
        idx = bad.nonzero().flatten()
        finer = params.refined(4**level)
        # the split-step graphs take the step counts as an argument, so the compiled ones serve
        # the refinement too (eager, its 4x steps cost seconds a round trip at the four-controller
        # start); DOP853 would compile a new graph per step count, so it refines eagerly
        u_b, v_b, err_b = _propagate_fixed(u[idx], v[idx], K[idx], finer, compile and params.integrator == "split",
                                           None if cavity is None else cavity[idx])
        u_out, v_out, error = u_out.clone(), v_out.clone(), error.clone()
        u_out[idx], v_out[idx], error[idx] = u_b, v_b, err_b
    return u_out, v_out


def round_trip(u: torch.Tensor, v: torch.Tensor, angles: torch.Tensor, K, params: CavityParams, *,
               compile: bool = False, refine: bool = True, cavity: torch.Tensor | None = None):
    """One cavity round trip: propagate over z in [0, Z], then apply J1 JP J2 J3.

    Args:
        u, v: (B, n) complex64 or complex128 fields.
        angles: (B, 4) radians, order (alpha1, alpha2, alpha3, alpha_p).
        K: (B,) birefringence (or a scalar).
        params: cavity parameters.
        compile, refine, cavity: see ``propagate``.
    Returns:
        (u, v) after the round trip, same shape and dtype.
    """
    check_fields(u, v, params)
    angles = as_batch(angles, u.shape[0], "angles", u, width=4)
    cavity = check_cavity(cavity, u.shape[0], params)
    return _round_trip(u, v, angles, as_batch(K, u.shape[0], "K", u), params, compile, refine, cavity)


def _round_trip(u, v, angles: torch.Tensor, K: torch.Tensor, params: CavityParams, compile: bool, refine: bool,
                cavity: torch.Tensor | None = None):
    """``round_trip`` of fields, (B, 4) angles, (B,) K and per-cavity values that are already checked."""
    u, v = _propagate(u, v, K, params, compile, refine, cavity=cavity)
    return apply_jones(cavity_jones(angles, u.dtype), u, v)
