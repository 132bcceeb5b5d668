"""Batched cavity round trip on torch FFTs.

Integrator: an explicit Runge-Kutta method in the interaction picture of the
linear, diagonal-in-Fourier part of the propagation (an "integrating factor" RK,
here with the 12-stage, 8th-order Dormand-Prince DOP853 tableau at a fixed step).
The saturable gain g(E) multiplies a fixed spectral shape S(k) = 1 - tau k^2, so
its effect over a partial step s is exp(G(s) S) with G(s) = int_0^s g(E(z')) dz'.
G is carried as an extra ODE state, which keeps the transformation exact:

    u^(s) = exp((-i D k^2/2 -/+ i K - Gamma) s + G(s) S) w^(s)      (- for u, + for v)
    dw^/ds = exp(-(...)) F[N(u, v)],      dG/ds = g(E) = 2 g0 / (1 + E/E0)
    N(u, v) = i[(|u|^2 + A|v|^2) u + B v^2 u*,  (A|u|^2 + |v|^2) v + B u^2 v*]

Only the non-stiff Kerr terms are integrated by the Runge-Kutta stages;
dispersion, birefringence, loss and the gain filter are exact. Why 8th order:
the Kerr phase rotates fields by several radians per round trip; on the reference
cases, with the carrier rotation moved into the integrating factor (see ``_Step``),
fixed-step DOP853 reaches a relative error below 1e-5 with 48 evaluations per round
trip, where classical RK4 at the same cost stays above 3e-4.

Speed: complex ``exp`` is slow on CPU, so the dispersion phases exp(-i D k^2 c h/2)
are tabulated once per parameter set, the per-cavity rotations (K, omega) are scalar
cos/sin, the gain factor is a real exp, and all elementwise work is written in real
arithmetic on ``view_as_real`` tensors so that ``torch.compile`` can fuse a whole
step into one graph (Inductor does not generate code for complex ops; the FFTs stay
extern calls inside the graph). Compilation is opt-in (``compile=True``).
"""
from __future__ import annotations

import functools

import numpy as np
import torch

from laserrl.physics.jones import apply_jones, cavity_jones
from laserrl.physics.params import CavityParams

__all__ = ["propagate", "round_trip", "trapezoid_energy", "check_fields", "as_batch"]


def _dop853_tableau():
    # The Butcher tableau is taken from scipy rather than retyped.
    from scipy.integrate._ivp import dop853_coefficients as dc

    s = dc.N_STAGES
    return (np.asarray(dc.A[:s, :s], float), np.asarray(dc.B, float), np.asarray(dc.C[:s], float),
            np.asarray(dc.E5[:s], float), np.asarray(dc.E3[:s], float))


_A, _B, _C, _E5, _E3 = _dop853_tableau()
_STAGES = len(_C)


def _real_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.complex128 else torch.float32


def trapezoid_energy(power: torch.Tensor, dt: float) -> torch.Tensor:
    """Trapezoid rule over the last axis of the n samples (not a periodic sum)."""
    return dt * (power.sum(-1) - 0.5 * (power[..., 0] + power[..., -1]))


def check_fields(u, v, params: CavityParams) -> None:
    """Raise a ValueError naming the field if u, v are not matching (B, n) complex tensors."""
    for name, x in (("u", u), ("v", v)):
        if not torch.is_tensor(x) or not x.is_complex():
            raise ValueError(f"field {name} must be a complex tensor, got {getattr(x, 'dtype', type(x).__name__)}")
        if x.ndim != 2 or x.shape[-1] != params.n:
            raise ValueError(f"field {name} must have shape (B, n={params.n}), got {tuple(x.shape)}")
    if u.shape != v.shape or u.dtype != v.dtype or u.device != v.device:
        raise ValueError(
            f"fields u and v must match in shape, dtype and device, got {tuple(u.shape)}/{u.dtype} and {tuple(v.shape)}/{v.dtype}"
        )


def as_batch(x, batch: int, name: str, like: torch.Tensor, width: int | None = None) -> torch.Tensor:
    """Broadcast a scalar (or (width,) vector) to (B,) or (B, width) real, checking the shape."""
    if not torch.is_tensor(x):  # python floats stay float64 until cast below
        x = torch.as_tensor(np.asarray(x, dtype=np.float64) if not isinstance(x, complex) else x)
    x = x.to(device=like.device)
    if x.is_complex():
        raise ValueError(f"{name} must be real, got {x.dtype}")
    x = x.to(_real_dtype(like.dtype))
    want = (batch,) if width is None else (batch, width)
    if tuple(x.shape) != want:
        if x.ndim == (0 if width is None else 1) and (width is None or x.shape[-1] == width):
            x = x.expand(want)
        else:
            raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
    return x


# ---------------------------------------------------------------------------
# One DOP853 step in the interaction picture, real arithmetic on (..., 2) = (re, im)
# views so that Inductor can fuse it (FFTs stay extern calls in the same graph).
# ---------------------------------------------------------------------------
def _ifft_planar(re: torch.Tensor, im: torch.Tensor):
    z = torch.fft.ifft(torch.complex(re, im))
    return z.real, z.imag


def _fft_planar(re: torch.Tensor, im: torch.Tensor):
    z = torch.fft.fft(torch.complex(re, im))
    return z.real, z.imag


class _Step:
    """h-step of the IF-DOP853 scheme for fixed (params, dtype, device).

    Complex quantities are held as planar (real, imaginary) pairs of (B, 2, n) real
    tensors, interleaved only for the FFTs: Inductor vectorises planar arithmetic
    but not stores into an interleaved complex layout.

    The carrier rotation omega (the power-weighted mean Kerr frequency at the start of
    the step, sum P^2 / sum P with P = |u|^2 + |v|^2) is moved from the nonlinear
    term into the integrating factor: N -> N - i omega u, Lambda -> Lambda + i omega.
    This is exact for any constant omega and removes most of the phase that the
    Runge-Kutta stages would otherwise have to follow (about 40x smaller error at
    the same cost on the reference cases).
    """

    def __init__(self, params: CavityParams, real_dtype: torch.dtype, device: torch.device):
        k = params.wavenumbers(dtype=torch.float64)
        h = params.Z / params.z_steps
        offsets = np.append(_C, 1.0) * h  # stage offsets c_i h, then h for the final map
        disp = (-0.5 * params.D) * k**2  # -D k^2 / 2
        angle = torch.as_tensor(offsets)[:, None] * disp[None, :]  # (S+1, n)
        as_dev = dict(dtype=real_dtype, device=device)
        self.disp_cos = torch.cos(angle).to(**as_dev)
        self.disp_sin = torch.sin(angle).to(**as_dev)
        self.shape = (1.0 - params.tau * k**2).to(**as_dev)  # gain filter S(k)
        self.offsets = [float(o) for o in offsets]
        self.a = [[(j, float(_A[i, j]) * h) for j in range(i) if _A[i, j] != 0.0] for i in range(_STAGES)]
        self.b = [(j, float(_B[j]) * h) for j in range(_STAGES) if _B[j] != 0.0]
        self.e5 = [(j, float(_E5[j]) * h) for j in range(_STAGES) if _E5[j] != 0.0]
        self.e3 = [(j, float(_E3[j]) * h) for j in range(_STAGES) if _E3[j] != 0.0]
        self.sign = torch.tensor([1.0, -1.0], **as_dev)[:, None]  # -K for u, +K for v
        self.p = params

    def _factor(self, i: int, G: torch.Tensor, rate: torch.Tensor):
        """Planar exp(Lambda' s_i + G S) = (cos, sin) * amp, each (B, 2, n), and amp."""
        s = self.offsets[i]
        amp = torch.exp(G[:, None, None] * self.shape - self.p.Gamma * s)  # (B, 1, n)
        c, sn = torch.cos(rate * s)[..., None], torch.sin(rate * s)[..., None]  # (B, 2, 1)
        dc, ds = self.disp_cos[i], self.disp_sin[i]
        return (dc * c - ds * sn), (dc * sn + ds * c), amp

    def _kerr(self, ur, ui, vr, vi, omega: torch.Tensor):
        """N(u, v) - i omega (u, v) as planar (re, im) of (B, 2, n), and g(E) of the fields."""
        A, B = self.p.A, self.p.B
        pu = ur * ur + ui * ui
        pv = vr * vr + vi * vi
        v2r, v2i = vr * vr - vi * vi, 2 * vr * vi  # v^2
        u2r, u2i = ur * ur - ui * ui, 2 * ur * ui  # u^2
        om = omega[:, None]
        fu = pu + A * pv - om
        fv = A * pu + pv - om
        nu_r = fu * ur + B * (v2r * ur + v2i * ui)  # (|u|^2 + A|v|^2 - omega) u + B v^2 u*
        nu_i = fu * ui + B * (v2i * ur - v2r * ui)
        nv_r = fv * vr + B * (u2r * vr + u2i * vi)
        nv_i = fv * vi + B * (u2i * vr - u2r * vi)
        power = pu + pv
        energy = self.p.dt * (power.sum(-1) - 0.5 * (power[:, 0] + power[:, -1]))
        gain = (2.0 * self.p.g0) / (1.0 + energy / self.p.E0)
        # times i: (re, im) -> (-im, re)
        return torch.stack([-nu_i, -nv_i], 1), torch.stack([nu_r, nv_r], 1), gain

    def __call__(self, wr: torch.Tensor, wi: torch.Tensor, K: torch.Tensor):
        """Advance the Fourier-space fields (wr + i wi, each (B, 2, n)) by h."""
        xr, xi = _ifft_planar(wr, wi)
        power = (xr.square() + xi.square()).sum(1)  # (B, n): |u|^2 + |v|^2
        omega = power.square().sum(-1) / power.sum(-1).clamp_min(1e-30)
        rate = omega[:, None] - K[:, None] * self.sign.squeeze(-1)  # (B, 2) scalar rotation rates
        kr, ki, gs = [], [], []
        g_lo = g_hi = None
        for i in range(_STAGES):
            if i > 0:
                fr, fi, amp, yr, yi = self._map_stage(i, self.a[i], wr, wi, kr, ki, gs, g_lo, g_hi, rate)
                xr, xi = _ifft_planar(yr, yi)
            nr, ni, g = self._kerr(xr[:, 0], xi[:, 0], xr[:, 1], xi[:, 1], omega)
            nr, ni = _fft_planar(nr, ni)
            if i > 0:  # multiply by the inverse factor conj(f) / amp
                nr, ni = (nr * fr + ni * fi) / amp, (ni * fr - nr * fi) / amp
            kr.append(nr)
            ki.append(ni)
            gs.append(g)
            g_lo, g_hi = (g, g) if i == 0 else (torch.minimum(g_lo, g), torch.maximum(g_hi, g))
        # DOP853's embedded error estimate of this step (as in scipy), relative to |w|
        err5 = self._norm(self._combine(self.e5, kr, ki))
        err3 = self._norm(self._combine(self.e3, kr, ki))
        denom = torch.sqrt(err5.square() + 0.01 * err3.square()).clamp_min(1e-30)
        wr_new, wi_new = self._combine(self.b, kr, ki, wr, wi)
        error = err5.square() / denom / self._norm((wr_new, wi_new)).clamp_min(1e-30)
        _, _, _, yr, yi = self._map_stage(_STAGES, self.b, wr, wi, kr, ki, gs, g_lo, g_hi, rate)
        return yr, yi, error

    def _map_stage(self, i: int, coefs, wr, wi, kr, ki, gs, g_lo, g_hi, rate):
        """Interaction-picture state w + sum_j c_j k_j at offset s_i, mapped to the physical
        Fourier field by exp(Lambda' s_i + G S); also returns the factor (fr, fi, amp)."""
        yr, yi = self._combine(coefs, kr, ki, wr, wi)
        G = 0.0
        for j, c in coefs:
            G = G + c * gs[j]
        # G(s) = int_0^s g lies between s*min(g) and s*max(g). The tableau's large
        # coefficients (|a| sums up to ~96) can throw the estimate far outside when
        # g changes fast within a step, and exp(G S) with S ~ -17 then overflows;
        # clamping to the bracket keeps the factor finite and is inactive otherwise.
        s_i = self.offsets[i]
        G = torch.minimum(torch.maximum(G, s_i * g_lo), s_i * g_hi)
        fr, fi, amp = self._factor(i, G, rate)
        return fr, fi, amp, (yr * fr - yi * fi) * amp, (yr * fi + yi * fr) * amp

    @staticmethod
    def _combine(coefs, kr, ki, start_r=0.0, start_i=0.0):
        """start + sum_j c_j k_j for (j, c) in coefs, as planar (re, im)."""
        er, ei = start_r, start_i
        for j, c in coefs:
            er = er + c * kr[j]
            ei = ei + c * ki[j]
        return er, ei

    @staticmethod
    def _norm(pair):
        re, im = pair
        return torch.sqrt((re.square() + im.square()).sum((-1, -2)))


@functools.lru_cache(maxsize=16)
def _stepper(params: CavityParams, real_dtype: torch.dtype, device: torch.device, compiled: bool):
    step = _Step(params, real_dtype, device)
    if compiled:
        return torch.compile(step.__call__, fullgraph=True, dynamic=None)
    return step.__call__


def _propagate_fixed(u, v, K: torch.Tensor, params: CavityParams, compile: bool):
    """Fixed-step propagation; returns (u, v, error) with DOP853's largest step error estimate."""
    rdt = _real_dtype(u.dtype)
    step = _stepper(params, rdt, u.device, bool(compile))
    w = torch.fft.fft(torch.stack([u, v], dim=-2))
    wr, wi = w.real.contiguous(), w.imag.contiguous()
    if compile:
        # only the batch size varies (active subsets shrink as cavities converge); n and
        # the stage count stay static so Inductor can vectorise along t
        for x in (wr, wi, K):
            torch._dynamo.mark_dynamic(x, 0)
    error = torch.zeros_like(K)
    for _ in range(params.z_steps):
        wr, wi, step_error = step(wr, wi, K)
        error = torch.maximum(error, step_error)
    x = torch.fft.ifft(torch.complex(wr, wi))
    return x[:, 0], x[:, 1], error


#: Step error estimate above which a cavity's propagation is redone with finer steps.
#: Ordinary states estimate 1e-6..1e-4 at the default 4 steps; an unstable step (intense
#: or fast-changing states) shows up orders of magnitude above that before it blows up.
REFINE_ERROR = 1e-3


def propagate(u: torch.Tensor, v: torch.Tensor, K, params: CavityParams, *, compile: bool = False,
              refine: bool = True, max_refinements: int = 3):
    """Propagate a batch of fields over z in [0, Z] (no Jones matrices).

    Args:
        u, v: (B, n) complex64 or complex128 fields.
        K: birefringence, a (B,) tensor or a scalar.
        params: cavity parameters; ``params.z_steps`` fixed DOP853 steps of h = Z / z_steps.
        compile: fuse the step with ``torch.compile`` (one-off compilation of tens of
            seconds per process and batch-shape family, then several times faster).
        refine: redo cavities whose embedded error estimate exceeds ``REFINE_ERROR`` (or
            that came out non-finite) with 4x finer steps, up to ``max_refinements`` times.
            Costs one host synchronisation.
    Returns:
        (u, v) at z = Z.
    """
    check_fields(u, v, params)
    K = as_batch(K, u.shape[0], "K", u)
    u_out, v_out, error = _propagate_fixed(u, v, K, params, compile)
    if not refine:
        return u_out, v_out
    for level in range(1, max_refinements + 1):
        bad = ~(error <= REFINE_ERROR)  # also catches NaN
        if not bool(bad.any()):
            break
        idx = bad.nonzero().flatten()
        finer = params.replace(z_steps=params.z_steps * 4**level)
        u_b, v_b, err_b = _propagate_fixed(u[idx], v[idx], K[idx], finer, False)
        u_out, v_out, error = u_out.clone(), v_out.clone(), error.clone()
        u_out[idx], v_out[idx], error[idx] = u_b, v_b, err_b
    return u_out, v_out


def round_trip(u: torch.Tensor, v: torch.Tensor, angles: torch.Tensor, K, params: CavityParams, *,
               compile: bool = False, refine: bool = True):
    """One cavity round trip: propagate over z in [0, Z], then apply J1 JP J2 J3.

    Args:
        u, v: (B, n) complex64 or complex128 fields.
        angles: (B, 4) radians, order (alpha1, alpha2, alpha3, alpha_p).
        K: (B,) birefringence (or a scalar).
        params: cavity parameters.
        compile, refine: see ``propagate``.
    Returns:
        (u, v) after the round trip, same shape and dtype.
    """
    check_fields(u, v, params)
    angles = as_batch(angles, u.shape[0], "angles", u, width=4)
    u, v = propagate(u, v, K, params, compile=compile, refine=refine)
    return apply_jones(cavity_jones(angles, u.dtype), u, v)
