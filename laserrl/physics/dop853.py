"""DOP853 integrating-factor integrator of the propagation over z in [0, Z] (``integrator="dop853"``).

An explicit Runge-Kutta method in the interaction picture of the linear,
diagonal-in-Fourier part of the propagation (an "integrating factor" RK), here with the
12-stage, 8th-order Dormand-Prince DOP853 tableau at a fixed step h = Z / z_steps.
The saturable gain g(E) multiplies a fixed spectral shape S(k) = 1 - tau k^2, so its
effect over a partial step s is exp(G(s) S) with G(s) = int_0^s g(E(z')) dz'.
G is carried as an extra ODE state, which keeps the transformation exact:

    u^(s) = exp((-i D k^2/2 -/+ i K - Gamma) s + G(s) S) w^(s)      (- for u, + for v)
    dw^/ds = exp(-(...)) F[N(u, v)],      dG/ds = g(E) = 2 g0 / (1 + E/E0)
    N(u, v) = i[(|u|^2 + A|v|^2) u + B v^2 u*,  (A|u|^2 + |v|^2) v + B u^2 v*]

Only the non-stiff Kerr terms are integrated by the Runge-Kutta stages; dispersion,
birefringence, loss and the gain filter are exact. Why 8th order: the Kerr phase
rotates fields by several radians per round trip; on the reference cases, with the
carrier rotation moved into the integrating factor (see ``_Step``), fixed-step DOP853
reaches a relative error below 1e-5 with 48 evaluations per round trip, where
classical RK4 at the same cost stays above 3e-4.

Speed: complex ``exp`` is slow on CPU, so the dispersion phases exp(-i D k^2 c h/2)
are tabulated once per parameter set, the per-cavity rotations (K, omega) are scalar
cos/sin, the gain factor is a real exp, and all elementwise work is written in real
arithmetic on planar (re, im) tensors so that ``torch.compile`` can fuse a whole step
into one graph (Inductor does not generate code for complex ops; the FFTs stay extern
calls inside the graph).

``_stepper`` is the cached round-trip stepper of both integrators: for
``integrator="split"`` it hands over to ``laserrl.physics.split_step``.
"""
from __future__ import annotations

import functools

import numpy as np
import torch

from laserrl.physics.fft_layout import _fft_planar, _ifft_planar
from laserrl.physics.params import CavityParams
from laserrl.physics.split_step import _split_stepper


def _dop853_tableau():
    # The Butcher tableau is taken from scipy rather than retyped.
    from scipy.integrate._ivp import dop853_coefficients as dc

    s = dc.N_STAGES
    return (np.asarray(dc.A[:s, :s], float), np.asarray(dc.B, float), np.asarray(dc.C[:s], float),
            np.asarray(dc.E5[:s], float), np.asarray(dc.E3[:s], float))


_A, _B, _C, _E5, _E3 = _dop853_tableau()
_STAGES = len(_C)


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
    """fn(w, K) -> (w, error) over one round trip of the Fourier-space fields w (complex,
    (B, 2, n)), for params with any z_steps."""
    if params.integrator == "split":
        # the step counts are an argument, so refinements reuse the compiled graphs
        split = _split_stepper(params.replace(z_steps=1, z_steps_coarse=None), real_dtype, device, compiled)
        return functools.partial(split, passes=params.split_passes)
    step = _Step(params, real_dtype, device)

    def steps(wr, wi, K):
        error = torch.zeros_like(K)
        for _ in range(params.z_steps):
            wr, wi, step_error = step(wr, wi, K)
            error = torch.maximum(error, step_error)
        return wr, wi, error
    if compiled:
        steps = torch.compile(steps, fullgraph=True, dynamic=None)

    def fn(w, K):
        wr, wi = w.real.contiguous(), w.imag.contiguous()
        if compiled:  # only the batch size varies (see split_step._SplitStep.__call__)
            for x in (wr, wi, K):
                torch._dynamo.mark_dynamic(x, 0)
        wr, wi, error = steps(wr, wi, K)
        return torch.complex(wr, wi), error
    return fn
