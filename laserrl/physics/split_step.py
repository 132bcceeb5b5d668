"""Split-step integrator of the propagation over z in [0, Z] (the default, ``integrator="split"``).

Strang splitting into two exactly solved flows, L(h/2) [N(h) L(h)]^(steps-1) N(h) L(h/2)
with h = Z / steps, at ``steps`` and ``2 steps``; Strang splitting is symmetric, so one
Richardson extrapolation, (4 fine - coarse) / 3, makes it fourth order.

Linear flow L(s), exact in Fourier space (dispersion, birefringence, loss and the
saturable, bandwidth-limited gain):

    u^(s) = exp((-i D k^2/2 -/+ i K - Gamma) s + G(s) S) u^(0),   S = 1 - tau k^2,   (- for u, + for v)
    dG/ds = g(E(s)) = 2 g0 / (1 + E(s)/E0),

where E(s) is the trapezoid energy of the fields at s. E(s) is an explicit function of
G(s) (Parseval, minus the trapezoid end-point halves, which are evaluated from the
Fourier coefficients), so the scalar ODE for G is solved by one classical RK4 step per
flow. (Lower-order rules for G, or freezing the end-point share of the energy, cost
3-10x in accuracy on the reference cases: E changes by tens of percent per round trip.)

Kerr flow N(s), exact pointwise: for A + B = 1 (an isotropic Kerr medium; silica's
A = 2/3, B = 1/3) the circular components a = u + i v, b = u - i v only change phase,

    a(s) = a exp(i s (A|a|^2 + (1 + B)|b|^2) / 2),   b likewise with a <-> b,

(the 1/2 because a, b are not normalised by sqrt 2), so |a|, |b| and the local power
are exactly conserved.
"""
from __future__ import annotations

import functools

import torch

from laserrl.physics.fft_layout import _pack_bits, _unpack_bits, _uses_bits, fft_bits, fft_planar
from laserrl.physics.observables import trapezoid_energy
from laserrl.physics.params import CavityParams


class _SplitStep:
    """Strang splitting with exact sub-flows for fixed (params, dtype, device).

    Complex quantities are planar (real, imaginary) pairs of real tensors inside the flows so
    that ``torch.compile`` fuses the elementwise work (Inductor does not generate code for
    complex operators). Between the compiled calls, and into and out of the FFTs, the
    Fourier-space fields travel as a *carrier*: on CPU with complex64 and compilation, one
    int64 (B, 2, n) tensor whose memory is the complex64 fields (``_pack_bits``), which the
    compiled kernels pack and unpack with vectorised integer operations and which
    ``fft_bits`` transforms in place of a copy; otherwise a planar pair (re, im) of (B, 2, n)
    tensors transformed by the ``fft_planar`` custom op. Flow lengths are 0-d tensors, so
    one compiled graph serves every step size (and refinement level) rather than one
    unrolled round trip per step count.
    """

    def __init__(self, params: CavityParams, real_dtype: torch.dtype, device: torch.device, compiled: bool):
        self.p = params
        as_dev = dict(dtype=real_dtype, device=device)
        k = params.wavenumbers(dtype=torch.float64)
        self.disp = (-0.5 * params.D) * k**2  # -D k^2 / 2, float64 for the host tables
        self.shape = (1.0 - params.tau * k**2).to(**as_dev)  # gain filter S(k)
        self.as_dev = as_dev
        self._tables = {}
        self.packed = _uses_bits(real_dtype, device, compiled)
        self.compiled = compiled
        self.first_linear_fn, self.stage_fn = self.first_linear, self.stage
        if compiled:
            self.first_linear_fn = torch.compile(self.first_linear, fullgraph=True, dynamic=None)
            self.stage_fn = torch.compile(self.stage, fullgraph=True, dynamic=None)

    # --- the carrier of the Fourier-space fields -----------------------------------------
    def _from_complex(self, w: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return (w.view(torch.int64),) if self.packed else (w.real.contiguous(), w.imag.contiguous())

    def _to_complex(self, state) -> torch.Tensor:
        return state[0].view(torch.complex64) if self.packed else torch.complex(*state)

    def _planar(self, state):
        """(re, im), each (B, 2, n), of the carried fields."""
        return _unpack_bits(state[0]) if self.packed else state

    def _carrier(self, fields):
        """The carrier of [(re, im) of u, (re, im) of v], each part (B, n). Stacking per field
        lets Inductor write every part straight into the carrier instead of first into planar
        (B, 2, n) buffers of its own."""
        if self.packed:
            return (torch.stack([_pack_bits(re, im) for re, im in fields], 1),)
        return torch.stack([re for re, _ in fields], 1), torch.stack([im for _, im in fields], 1)

    def _transform(self, state, inverse: bool):
        """Planar (re, im) of the (inverse) FFT of the carried fields."""
        if self.packed:
            return _unpack_bits(fft_bits(state[0], inverse))
        return fft_planar(*state, inverse)

    def _table(self, s: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The length s as a 0-d tensor, and a (6, n) table for a linear flow over s:
        cos, sin of the dispersion phase over s, then the inverse-DFT rows (with ifft's
        1/n) of the end samples t_0 and t_{n-1} rotated by that phase, as (re, im).
        Precomputed on the host: inside the graph Inductor would recompute these
        transcendentals for every cavity."""
        if s not in self._tables:
            disp = self.disp  # float64
            rotation = torch.exp(1j * s * disp) / self.p.n
            j = torch.arange(self.p.n, dtype=torch.float64)
            first, last = rotation, rotation * torch.exp(-2j * torch.pi * j / self.p.n)
            table = torch.stack([torch.cos(s * disp), torch.sin(s * disp), first.real, first.imag,
                                 last.real, last.imag])
            self._tables[s] = (torch.tensor(s, **self.as_dev), table.to(**self.as_dev))
        return self._tables[s]

    def _gain_rate(self, Ur, Ui, spectral_power, G, rows, s):
        """g(E) of the fields u^ exp(i disp s + G S - Gamma s), (B,); K's phase does not change E.
        rows: (4, n) end-sample rows rotated by the dispersion phase over s."""
        p = self.p
        amp = torch.exp(G[:, None] * self.shape)  # (B, n)
        periodic = (spectral_power * amp.square()).sum(-1) / p.n  # sum_j |u_j|^2 by Parseval
        ends = 0.0
        # |u|^2 + |v|^2 at t_0 and t_{n-1}: every reduction is over the last axis of a (B, n)
        # tensor (one field at a time), the same shape as the periodic sum, which lets Inductor
        # emit fewer, larger loop nests than (B, 2) sums
        for f in (0, 1):
            yr, yi = Ur[:, f] * amp, Ui[:, f] * amp
            for rr, ri in ((rows[0], rows[1]), (rows[2], rows[3])):
                er = (yr * rr - yi * ri).sum(-1)
                ei = (yr * ri + yi * rr).sum(-1)
                ends = ends + er.square() + ei.square()
        energy = p.dt * (periodic - 0.5 * ends) * torch.exp(-2.0 * p.Gamma * s)
        return (2.0 * p.g0) / (1.0 + energy / p.E0)

    def linear(self, Ur, Ui, K, s, table, half_table, energy0):
        """Exact linear flow L(s) of the Fourier-space fields (planar, each (B, 2, n)), returned
        as the carrier.

        s: 0-d tensor; table, half_table: ``_table(s)`` and ``_table(s/2)``;
        energy0: (B,) trapezoid energy at the start of the flow."""
        P = (Ur.square() + Ui.square()).sum(1)  # (B, n)
        k1 = (2.0 * self.p.g0) / (1.0 + energy0 / self.p.E0)
        half = 0.5 * s
        k2 = self._gain_rate(Ur, Ui, P, half * k1, half_table[2:], half)
        k3 = self._gain_rate(Ur, Ui, P, half * k2, half_table[2:], half)
        k4 = self._gain_rate(Ur, Ui, P, s * k3, table[2:], s)
        G = (s / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        amp = torch.exp(G[:, None] * self.shape - self.p.Gamma * s)  # (B, n)
        dc, ds = table[0], table[1]
        fields = []
        for f, sign in ((0, -1.0), (1, 1.0)):  # -K s for u, +K s for v
            rot = (sign * s) * K
            rc, rs = torch.cos(rot)[:, None], torch.sin(rot)[:, None]
            c, sn = (dc * rc - ds * rs) * amp, (ds * rc + dc * rs) * amp  # exp(i (disp -/+ K) s) * amp
            ur, ui = Ur[:, f], Ui[:, f]
            fields.append((ur * c - ui * sn, ur * sn + ui * c))
        return self._carrier(fields)

    def first_linear(self, state, K, s, table, half_table):
        """L(s) of carried fields whose time-domain energy is not at hand."""
        xr, xi = self._transform(state, inverse=True)
        energy0 = trapezoid_energy((xr.square() + xi.square()).sum(1), self.p.dt)
        return self.linear(*self._planar(state), K, s, table, half_table, energy0)

    def kerr(self, xr, xi, s):
        """Exact Kerr flow N(s) of the time-domain fields (B, 2, n): [(re, im) of u, of v]."""
        A, B = self.p.A, self.p.B
        ur, ui, vr, vi = xr[:, 0], xi[:, 0], xr[:, 1], xi[:, 1]
        ar, ai = ur - vi, ui + vr  # a = u + i v
        br, bi = ur + vi, ui - vr  # b = u - i v
        pa, pb = ar.square() + ai.square(), br.square() + bi.square()
        ta = (0.5 * s) * (A * pa + (1.0 + B) * pb)
        tb = (0.5 * s) * (A * pb + (1.0 + B) * pa)
        ca, sa, cb, sb = torch.cos(ta), torch.sin(ta), torch.cos(tb), torch.sin(tb)
        ar, ai = ar * ca - ai * sa, ar * sa + ai * ca
        br, bi = br * cb - bi * sb, br * sb + bi * cb
        # u = (a + b) / 2, v = -i (a - b) / 2
        return [(0.5 * (ar + br), 0.5 * (ai + bi)), (0.5 * (ai - bi), -0.5 * (ar - br))]

    def stage(self, state, K, h, s_after, table, half_table):
        """N(h) then L(s_after), from and to the carried Fourier-space fields."""
        xr, xi = self._transform(state, inverse=True)
        # N keeps |u|^2 + |v|^2 pointwise, so the energy after it is the energy before it;
        # summing N's input lets Inductor fuse the sum into the Kerr kernel instead of
        # storing N's output for a later pass
        energy0 = trapezoid_energy((xr.square() + xi.square()).sum(1), self.p.dt)
        Ur, Ui = self._transform(self._carrier(self.kerr(xr, xi, h)), inverse=False)
        return self.linear(Ur, Ui, K, s_after, table, half_table, energy0)

    def strang(self, state, K, steps: int):
        """L(h/2) [N(h) L(h)]^(steps-1) N(h) L(h/2) with h = Z / steps: second order."""
        h = self.p.Z / steps
        full, half, quarter = self._table(h), self._table(h / 2), self._table(h / 4)
        state = self.first_linear_fn(state, K, half[0], half[1], quarter[1])
        for i in range(steps):
            after, after_half = (full, half) if i < steps - 1 else (half, quarter)
            state = self.stage_fn(state, K, full[0], after[0], after[1], after_half[1])
        return state

    def __call__(self, w: torch.Tensor, K: torch.Tensor, steps: int):
        """Propagate the Fourier-space fields w (complex, (B, 2, n)) over z in [0, Z].

        Strang splitting is symmetric, so its global error expands in even powers of h
        and one Richardson extrapolation of the ``steps`` and ``2 steps`` passes,
        (4 fine - coarse) / 3, is fourth order. Returns the extrapolated fields and
        |fine - coarse| / |fine|, an estimate of the second-order splitting error that
        flags unresolved states.
        """
        state = self._from_complex(w)
        if self.compiled:
            # only the batch size varies (active subsets shrink as cavities converge); n and
            # the stage count stay static so Inductor can vectorise along t
            for x in (*state, K):
                torch._dynamo.mark_dynamic(x, 0)
        # real views: torch's eager complex arithmetic is slower than real
        coarse = torch.view_as_real(self._to_complex(self.strang(state, K, steps)))
        fine = torch.view_as_real(self._to_complex(self.strang(state, K, 2 * steps)))
        diff = fine - coarse
        dims = (-1, -2, -3)
        error = torch.linalg.vector_norm(diff, dim=dims) / torch.linalg.vector_norm(fine, dim=dims).clamp_min(1e-15)
        return torch.view_as_complex(fine.add(diff, alpha=1.0 / 3.0)), error


@functools.lru_cache(maxsize=16)
def _split_stepper(params: CavityParams, real_dtype: torch.dtype, device: torch.device, compiled: bool):
    return _SplitStep(params, real_dtype, device, compiled)
