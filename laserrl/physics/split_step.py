"""Split-step integrator of the propagation over z in [0, Z] (the default, ``integrator="split"``).

Strang splitting into two exactly solved flows, L(h/2) [N(h) L(h)]^(N-1) N(h) L(h/2)
with h = Z / N, in two independent passes of N1 and N2 steps (``CavityParams.split_passes``:
10 and 16 by default). Strang splitting is symmetric, so its error expands in even powers,
c h^2 + d h^4 + ..., and one Richardson extrapolation

    u = (N2^2 u_N2 - N1^2 u_N1) / (N2^2 - N1^2)

is fourth order, leaving about d Z^4 / (N1 N2)^2 at a cost of N1 + N2 stages. The pair
(10, 16) costs 26 stages against 24 for (8, 16) (0.92-0.93x the speed) and leaves 0.64x its
error: the (8, 16) pair's one-round-trip error reached 1.1e-4 to 1.2e-4 (against the 1e-4
bar) on the intense pulse of the second round trip from a sech start at K = 0.4, and 7e-5
to 8e-5 on the mode-locked pulses at K = 0.1 and 0.2; (10, 16) keeps these below 8e-5.
Pairs of closer step counts, such as (12, 14), leave a little less truncation error but
weight the two passes by up to 3.8 instead of 1.6, which multiplies complex64 rounding to
errors of up to 2e-5.

Unresolved spectra. The expansion in h holds only for modes whose dispersion phase over a
coarse step, |D| k^2 h1 / 2, is small. A white-noise start (``noise_fields``) has half its
power in modes turned by more than pi/2 per coarse step; the gain filter 1 - tau k^2 damps
them away during the round trip, but while they live the extrapolation is not fourth order
(the error falls about 4x, not 16x, per doubling of the steps) and the first round trip from
noise had errors of 2e-4 to 6e-4 at every K. Such fields are therefore flagged: when more
than ``UNRESOLVED_POWER`` of the input's power lies in modes with |D| k^2 h1 / 2 > pi/2, the
error estimate is infinite, so that ``laserrl.physics.cavity.propagate`` redoes the cavity
with 4x the steps (40 and 64 by default), whose coarse step resolves every mode of the grid
(error about 1e-5). Fields a round trip old hold at most 2e-4 of their power there (the broad,
intense states below), mode-locked pulses less than 1e-6.

Linear flow L(s), exact in Fourier space (dispersion, birefringence, loss and the
saturable, bandwidth-limited gain):

    u^(s) = exp((-i D k^2/2 -/+ i K - Gamma) s + G(s) S) u^(0),   S = 1 - tau k^2,   (- for u, + for v)
    dG/ds = g(E(s)) = 2 g0 / (1 + E(s)/E0),

where E(s) is the trapezoid energy of the fields at s. E(s) is an explicit function of
G(s) (Parseval, minus the trapezoid end-point halves, which are evaluated from the
Fourier coefficients), so the scalar ODE for G is solved by one classical RK4 step per
flow. (Lower-order rules for G, or freezing the end-point share of the energy, cost
3-10x in accuracy on the reference cases: E changes by tens of percent per round trip.)
The birefringence K is a phase in this exact flow; it is not split from anything.

Cavities of one batch may differ in D, E0, tau, g0 and Gamma (``cavity``, (B, 5) in the order
``CAVITY_KEYS``, for training on cavities other than the nominal one): then the dispersion
tables, the gain filter S and the gain's constants are per cavity, and every formula above
holds cavity by cavity.

Kerr flow N(s), exact pointwise: for A + B = 1 (an isotropic Kerr medium; silica's
A = 2/3, B = 1/3) the circular components a = u + i v, b = u - i v only change phase,

    a(s) = a exp(i s (A|a|^2 + (1 + B)|b|^2) / 2),   b likewise with a <-> b,

(the 1/2 because a, b are not normalised by sqrt 2), so |a|, |b| and the local power
are exactly conserved.

Known limit: broad states that fill a large part of the time window (energies of 14 to 120;
the four-controller start 15/-5/20/84 deg reaches them at K >= 0, and alpha1 >= 0 deg with
the paper's other angles) amplify the splitting error strongly (it falls with the dispersion
D cubed and about 50x per doubling of the steps); their one-round-trip error is 1e-4 to
2e-3 with (10, 16), and z_steps = 16 (passes of 20 and 32 steps, twice the cost) keeps it
below 4e-5. Neither the two-pass estimate |fine - coarse| (whose ratio to the extrapolated
error varies 100-fold between states) nor a third, coarser pass singles them out from
mode-locked pulses without also flagging a fifth or more of those.
"""
from __future__ import annotations

import functools
import math

import torch

from laserrl.physics.fft_layout import _pack_bits, _unpack_bits, _uses_bits, fft_bits, fft_planar
from laserrl.physics.observables import trapezoid_energy
from laserrl.physics.params import CavityParams

#: Share of a field's power in modes whose dispersion phase over one coarse step exceeds
#: pi/2 above which the extrapolation is not trusted (its error estimate becomes infinite).
#: White noise holds 0.43-0.51 there at the default resolution, fields a round trip old at
#: most 2e-4; 1e-3 of white noise adds about 1e-6 to the error.
UNRESOLVED_POWER = 1e-3

#: Compiled graphs per code object that a process may hold (torch._dynamo's recompile_limit).
RECOMPILE_LIMIT = 64



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
        self.k2 = params.wavenumbers(dtype=torch.float64) ** 2  # k^2, float64 for the host tables
        self.disp = (-0.5 * params.D) * self.k2  # -D k^2 / 2
        self.shape = (1.0 - params.tau * self.k2).to(**as_dev)  # gain filter S(k)
        self.as_dev = as_dev
        self._tables = {}
        self._unresolved = {}
        self.packed = _uses_bits(real_dtype, device, compiled)
        self.compiled = compiled
        self.first_linear_fn, self.stage_fn = self.first_linear, self.stage
        self.first_linear_cavity_fn, self.stage_cavity_fn = self.first_linear_cavity, self.stage_cavity
        if compiled:
            # each cavity (CavityParams), dtype and per-cavity variant is a graph of its own of these two
            # methods, all counted against one code object: a process that runs several cavities (an
            # evaluation on other cavities, the report, the tests) needs more than dynamo's default of 8
            torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, RECOMPILE_LIMIT)
            self.first_linear_fn = torch.compile(self.first_linear, fullgraph=True, dynamic=None)
            self.stage_fn = torch.compile(self.stage, fullgraph=True, dynamic=None)
            # per-cavity calls get code objects of their own: sharing one with the nominal calls makes
            # dynamo, when it recompiles, evaluate the other variant's guards on None (a TypeError)
            self.first_linear_cavity_fn = torch.compile(self.first_linear_cavity, fullgraph=True, dynamic=None)
            self.stage_cavity_fn = torch.compile(self.stage_cavity, fullgraph=True, dynamic=None)

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

    def _table(self, s: float, disp: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The length s as a 0-d tensor, and a (6, n) table for a linear flow over s:
        cos, sin of the dispersion phase over s, then the inverse-DFT rows (with ifft's
        1/n) of the end samples t_0 and t_{n-1} rotated by that phase, as (re, im).
        Precomputed on the host: inside the graph Inductor would recompute these
        transcendentals for every cavity. With per-cavity dispersion ``disp`` (B, n), float64,
        a (B, 6, n) table (not cached: it follows the cavities of the call)."""
        if disp is None and s in self._tables:
            return self._tables[s]
        own = disp if disp is not None else self.disp  # float64
        rotation = torch.exp(1j * s * own) / self.p.n
        j = torch.arange(self.p.n, dtype=torch.float64, device=own.device)
        first, last = rotation, rotation * torch.exp(-2j * torch.pi * j / self.p.n)
        table = torch.stack([torch.cos(s * own), torch.sin(s * own), first.real, first.imag,
                             last.real, last.imag], dim=-2)
        out = (torch.tensor(s, **self.as_dev), table.to(**self.as_dev))
        if disp is None:
            self._tables[s] = out
        return out

    def _per_cavity(self, cavity: torch.Tensor):
        """From per-cavity values (B, 5) (``CAVITY_KEYS``): their dispersion -D k^2 / 2 (B, n),
        float64, and what the flows take, (gain filter S (B, n), g0, E0, Gamma (B,) each)."""
        k2 = self.k2.to(cavity.device)
        c = cavity.to(torch.float64)
        D, E0, tau, g0, Gamma = c.unbind(-1)
        disp = (-0.5 * D)[:, None] * k2
        shape = 1.0 - tau[:, None] * k2
        return disp, tuple(x.to(**self.as_dev) for x in (shape, g0, E0, Gamma))

    def _constants(self, cavity):
        """(S, g0, E0, Gamma): the nominal cavity's, or the per-cavity tensors of ``_per_cavity``."""
        return (self.shape, self.p.g0, self.p.E0, self.p.Gamma) if cavity is None else cavity

    def _gain_rate(self, Ur, Ui, spectral_power, G, rows, s, cavity=None):
        """g(E) of the fields u^ exp(i disp s + G S - Gamma s), (B,); K's phase does not change E.
        rows: (4, n) end-sample rows rotated by the dispersion phase over s ((B, 4, n) per cavity)."""
        p = self.p
        shape, g0, E0, Gamma = self._constants(cavity)
        amp = torch.exp(G[:, None] * shape)  # (B, n)
        periodic = (spectral_power * amp.square()).sum(-1) / p.n  # sum_j |u_j|^2 by Parseval
        ends = 0.0
        # |u|^2 + |v|^2 at t_0 and t_{n-1}: every reduction is over the last axis of a (B, n)
        # tensor (one field at a time), the same shape as the periodic sum, which lets Inductor
        # emit fewer, larger loop nests than (B, 2) sums
        for f in (0, 1):
            yr, yi = Ur[:, f] * amp, Ui[:, f] * amp
            for rr, ri in ((rows[..., 0, :], rows[..., 1, :]), (rows[..., 2, :], rows[..., 3, :])):
                er = (yr * rr - yi * ri).sum(-1)
                ei = (yr * ri + yi * rr).sum(-1)
                ends = ends + er.square() + ei.square()
        energy = p.dt * (periodic - 0.5 * ends) * torch.exp(-2.0 * Gamma * s)
        return (2.0 * g0) / (1.0 + energy / E0)

    def linear(self, Ur, Ui, K, s, table, half_table, energy0, cavity=None):
        """Exact linear flow L(s) of the Fourier-space fields (planar, each (B, 2, n)), returned
        as the carrier.

        s: 0-d tensor; table, half_table: ``_table(s)`` and ``_table(s/2)``;
        energy0: (B,) trapezoid energy at the start of the flow; cavity: None (the nominal
        cavity) or the per-cavity tensors of ``_per_cavity``."""
        shape, g0, E0, Gamma = self._constants(cavity)
        loss = Gamma if cavity is None else Gamma[:, None]
        P = (Ur.square() + Ui.square()).sum(1)  # (B, n)
        k1 = (2.0 * g0) / (1.0 + energy0 / E0)
        half = 0.5 * s
        k2 = self._gain_rate(Ur, Ui, P, half * k1, half_table[..., 2:, :], half, cavity)
        k3 = self._gain_rate(Ur, Ui, P, half * k2, half_table[..., 2:, :], half, cavity)
        k4 = self._gain_rate(Ur, Ui, P, s * k3, table[..., 2:, :], s, cavity)
        G = (s / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        amp = torch.exp(G[:, None] * shape - loss * s)  # (B, n)
        dc, ds = table[..., 0, :], table[..., 1, :]
        fields = []
        for f, sign in ((0, -1.0), (1, 1.0)):  # -K s for u, +K s for v
            rot = (sign * s) * K
            rc, rs = torch.cos(rot)[:, None], torch.sin(rot)[:, None]
            c, sn = (dc * rc - ds * rs) * amp, (ds * rc + dc * rs) * amp  # exp(i (disp -/+ K) s) * amp
            ur, ui = Ur[:, f], Ui[:, f]
            fields.append((ur * c - ui * sn, ur * sn + ui * c))
        return self._carrier(fields)

    def first_linear(self, state, K, s, table, half_table, cavity=None):
        """L(s) of carried fields whose time-domain energy is not at hand."""
        xr, xi = self._transform(state, inverse=True)
        energy0 = trapezoid_energy((xr.square() + xi.square()).sum(1), self.p.dt)
        return self.linear(*self._planar(state), K, s, table, half_table, energy0, cavity)

    def first_linear_cavity(self, state, K, s, table, half_table, cavity):
        """``first_linear`` with per-cavity constants (compiled on its own)."""
        return self.first_linear(state, K, s, table, half_table, cavity)

    def stage_cavity(self, state, K, h, s_after, table, half_table, cavity):
        """``stage`` with per-cavity constants (compiled on its own)."""
        return self.stage(state, K, h, s_after, table, half_table, cavity)

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

    def stage(self, state, K, h, s_after, table, half_table, cavity=None):
        """N(h) then L(s_after), from and to the carried Fourier-space fields."""
        xr, xi = self._transform(state, inverse=True)
        # N keeps |u|^2 + |v|^2 pointwise, so the energy after it is the energy before it;
        # summing N's input lets Inductor fuse the sum into the Kerr kernel instead of
        # storing N's output for a later pass
        energy0 = trapezoid_energy((xr.square() + xi.square()).sum(1), self.p.dt)
        Ur, Ui = self._transform(self._carrier(self.kerr(xr, xi, h)), inverse=False)
        return self.linear(Ur, Ui, K, s_after, table, half_table, energy0, cavity)

    def strang(self, state, K, steps: int, cavity=None):
        """L(h/2) [N(h) L(h)]^(steps-1) N(h) L(h/2) with h = Z / steps: second order.
        cavity: None or the per-cavity (B, 5) values (``CAVITY_KEYS``)."""
        h = self.p.Z / steps
        disp, own = (None, None) if cavity is None else self._per_cavity(cavity)
        full, half, quarter = self._table(h, disp), self._table(h / 2, disp), self._table(h / 4, disp)
        if self.compiled and cavity is not None:  # per-cavity inputs follow the batch size too
            for x in (*own, full[1], half[1], quarter[1]):
                torch._dynamo.mark_dynamic(x, 0)
        if cavity is None:
            first, stage, extra = self.first_linear_fn, self.stage_fn, ()
        else:
            first, stage, extra = self.first_linear_cavity_fn, self.stage_cavity_fn, (own,)
        state = first(state, K, half[0], half[1], quarter[1], *extra)
        for i in range(steps):
            after, after_half = (full, half) if i < steps - 1 else (half, quarter)
            state = stage(state, K, full[0], after[0], after[1], after_half[1], *extra)
        return state

    def _unresolved_share(self, w: torch.Tensor, steps: int, D_scale: float = 1.0):
        """(B,) share of the power of the Fourier-space fields w in modes whose dispersion
        phase over a step Z / steps exceeds pi/2, or None if the grid has no such mode.
        D_scale: the largest |D| of the batch over the nominal one (per-cavity values)."""
        key = (steps, D_scale)
        if key not in self._unresolved:
            phase = self.disp.abs() * D_scale * (self.p.Z / steps)  # |D| k^2 h / 2
            mask = phase > 0.5 * torch.pi
            # one matrix product of the squared (re, im) parts of both fields gives the power
            # in those modes and in all modes (4x faster than abs().square() and two sums)
            cols = torch.stack([mask.repeat_interleave(2).repeat(2), torch.ones(4 * self.p.n, dtype=torch.bool)], 1)
            self._unresolved[key] = cols.to(dtype=w.real.dtype, device=w.device) if bool(mask.any()) else None
        cols = self._unresolved[key]
        if cols is None:
            return None
        power = torch.view_as_real(w).reshape(w.shape[0], -1).square() @ cols  # (B, 2)
        return power[:, 0] / power[:, 1].clamp_min(torch.finfo(power.dtype).tiny)

    def __call__(self, w: torch.Tensor, K: torch.Tensor, passes: tuple[int, int], cavity: torch.Tensor | None = None):
        """Propagate the Fourier-space fields w (complex, (B, 2, n)) over z in [0, Z].

        passes: (N1, N2), the Strang steps of the coarse and the fine pass (N1 < N2).
        Returns the Richardson extrapolation (N2^2 fine - N1^2 coarse) / (N2^2 - N1^2),
        fourth order, and |fine - coarse| / |fine|, an estimate of the second-order
        splitting error that flags unresolved states; it is infinite for fields with more
        than ``UNRESOLVED_POWER`` of their power beyond the coarse pass's resolution.
        cavity: None (every cavity the nominal one) or per-cavity values (B, 5), ``CAVITY_KEYS``.
        """
        n1, n2 = passes
        D_scale = 1.0
        if cavity is not None:  # rounded up, so that a few distinct masks serve every batch
            D_scale = max(1.0, math.ceil(float(cavity[:, 0].abs().max()) / abs(self.p.D) * 20) / 20) if self.p.D else 1.0
        share = self._unresolved_share(w, n1, D_scale)
        state = self._from_complex(w)
        if self.compiled:
            # only the batch size varies (active subsets shrink as cavities converge); n and
            # the stage count stay static so Inductor can vectorise along t
            for x in (*state, K, *(() if cavity is None else (cavity,))):
                torch._dynamo.mark_dynamic(x, 0)
        # real views: torch's eager complex arithmetic is slower than real
        coarse = torch.view_as_real(self._to_complex(self.strang(state, K, n1, cavity)))
        fine = torch.view_as_real(self._to_complex(self.strang(state, K, n2, cavity)))
        diff = fine - coarse
        dims = (-1, -2, -3)
        error = torch.linalg.vector_norm(diff, dim=dims) / torch.linalg.vector_norm(fine, dim=dims).clamp_min(1e-15)
        if share is not None:
            error = error.masked_fill(share > UNRESOLVED_POWER, float("inf"))
        return torch.view_as_complex(fine.add(diff, alpha=n1**2 / (n2**2 - n1**2))), error


@functools.lru_cache(maxsize=16)
def _split_stepper(params: CavityParams, real_dtype: torch.dtype, device: torch.device, compiled: bool):
    return _SplitStep(params, real_dtype, device, compiled)
