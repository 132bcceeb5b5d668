"""What a laboratory measures at the output of the laser: no phase, finite resolution, noise.

The state of the cavity is the pair of complex fields u, v (t in [-T/2, T/2), n samples). An
experiment sees neither; it has

* an optical spectrum analyser (OSA): the power spectral density of both polarisations,

      P(w) = (|U(w)|^2 + |V(w)|^2) / (2 pi),   U(w) = int u(t) exp(-i w t) dt ~ dt fft(u),

  so that int P dw = int (|u|^2 + |v|^2) dt (Parseval). It reads the power in ``spectrum_bins``
  equal bins of the band w in [-span/2, span/2] after the instrument's response, a Gaussian in w
  of full width at half maximum ``spectrum_resolution``:

      S_j = int_{bin j} (G * P)(w) dw,   then   S_j <- max(S_j (1 + sigma_S xi_j), 0) + f |eta_j|,

  with xi, eta standard normal: relative noise ``spectrum_noise`` (sigma_S) of each reading and
  the readings of an empty bin, of scale ``spectrum_floor`` (f, the analyser's sensitivity);
* a power meter: the pulse energy (average power times the round-trip time),

      W = int (|u|^2 + |v|^2) dt (1 + sigma_W xi),   clipped at 0,

  the trapezoid rule of the paper's E (E = sqrt(W) without noise), relative noise ``energy_noise``;
* an intensity autocorrelator (background-free, normalised to 1 at zero delay):

      A(tau) = int I(t) I(t - tau) dt / int I(t)^2 dt + sigma_A xi,   I = |u|^2 + |v|^2,

  periodic over the window, at ``autocorrelation_points`` delays evenly in
  [-autocorrelation_span/2, autocorrelation_span/2], additive noise ``autocorrelation_noise``
  (``autocorrelation_points = 0``: no autocorrelator).

The reward from these readings keeps the paper's form r = E / M4 (eq. 9), E = sqrt(W). The
paper's M4 is the kurtosis of |fft(phi)|, phi = sqrt(I): a statistic of the pulse's intensity
in time, not of its optical spectrum (the phase does not enter). Its measurable counterpart is
the autocorrelation's: by Wiener-Khinchin, fft(A) = |fft(I)|^2 / int I^2 over the whole window (the
autocorrelator's span samples part of it), so (``reward="autocorrelation"``)

      r_measured = sqrt(W) / M4(s),   s_k = |fft(A)_k|^(1/2) over the autocorrelator's points,
      M4(s) = mean((s - mean s)^4) / std(s)^4.

``reward="spectrum"`` takes s_j = sqrt(S_j) over the OSA's bins instead. Over 400 converged states
(random angles, K in [-0.2, 0.4]) the autocorrelation's r ranks states as the paper's r does
(Spearman 0.97 with 64 points and 1 % noise; it tells r >= 0.15 from the rest with a ROC AUC of
0.999), the spectrum's does not (Spearman 0.77, AUC 0.75 with 64 bins over |w| < 6): the optical
spectrum carries the phase, which the paper's M4 ignores (``laserrl.analysis.measured``, docs/measured.md).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields as dc_fields

import torch

from laserrl.physics.observables import kurtosis, trapezoid_energy
from laserrl.physics.params import CavityParams

__all__ = ["Instruments", "Measurement", "measure", "measured_reward", "spectrum_matrix"]


@dataclass(frozen=True)
class Instruments:
    """Settings of the instruments (see the module docstring); frequencies w and delays in the
    dimensionless units of the model (the grid resolves |w| < pi n / T, 13.4 by default).

    Attributes:
        spectrum_bins: OSA readings per spectrum.
        spectrum_span: width of the band the OSA reads, centred on w = 0.
        spectrum_resolution: FWHM of the OSA's Gaussian response in w; None: one bin.
        spectrum_noise: relative noise of each OSA reading (standard deviation).
        spectrum_floor: scale of the readings of an empty bin (the OSA's sensitivity).
        energy_noise: relative noise of the power meter.
        autocorrelation_points: delays the autocorrelator reads; 0: no autocorrelator.
        autocorrelation_span: width of the delay window, centred on 0.
        autocorrelation_noise: additive noise of the normalised autocorrelation.
        reward: the readings whose kurtosis is the reward's M4: "autocorrelation" or "spectrum".
    """

    spectrum_bins: int = 64
    spectrum_span: float = 12.0
    spectrum_resolution: float | None = None
    spectrum_noise: float = 0.01
    spectrum_floor: float = 1e-6
    energy_noise: float = 0.01
    autocorrelation_points: int = 64
    autocorrelation_span: float = 30.0
    autocorrelation_noise: float = 0.01
    reward: str = "autocorrelation"

    def __post_init__(self):
        if self.reward not in ("autocorrelation", "spectrum"):
            raise ValueError(f"reward must be 'autocorrelation' or 'spectrum', got {self.reward!r}")
        if self.reward == "autocorrelation" and not self.autocorrelation_points:
            raise ValueError("reward='autocorrelation' needs the autocorrelator (autocorrelation_points >= 4); "
                             "or take reward='spectrum'")
        for f in dc_fields(self):
            value = getattr(self, f.name)
            if f.name == "reward" or (f.name == "spectrum_resolution" and value is None):
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise ValueError(f"{f.name} must be a finite number, got {value!r}")
        for name, low in (("spectrum_bins", 4), ("autocorrelation_points", 0)):
            value = getattr(self, name)
            if int(value) != value or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
            object.__setattr__(self, name, int(value))
        if 0 < self.autocorrelation_points < 4:
            raise ValueError(f"autocorrelation_points must be 0 (none) or >= 4, got {self.autocorrelation_points!r}")
        for name in ("spectrum_span", "autocorrelation_span"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if self.spectrum_resolution is not None and not self.spectrum_resolution > 0:
            raise ValueError(f"spectrum_resolution must be > 0 (or null: one bin), got {self.spectrum_resolution!r}")
        for name in ("spectrum_noise", "spectrum_floor", "energy_noise", "autocorrelation_noise"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")

    def check_grid(self, params: CavityParams) -> None:
        """The band and the delays must lie on the simulation's grid."""
        band = 2 * math.pi * params.n / params.T  # the grid's whole band of w
        if self.spectrum_span > band:
            raise ValueError(f"spectrum_span ({self.spectrum_span:g}) must be <= the grid's band 2 pi n / T = {band:.4g}")
        if self.autocorrelation_points and self.autocorrelation_span > params.T:
            raise ValueError(f"autocorrelation_span ({self.autocorrelation_span:g}) must be <= the window T = {params.T:g}")

    @property
    def resolution(self) -> float:
        return self.spectrum_resolution if self.spectrum_resolution is not None else self.spectrum_span / self.spectrum_bins


@dataclass
class Measurement:
    """One reading of every instrument, per cavity: ``spectrum`` (B, bins) OSA powers,
    ``energy`` (B,) the power meter's W, ``autocorrelation`` (B, points) or None."""

    spectrum: torch.Tensor
    energy: torch.Tensor
    autocorrelation: torch.Tensor | None


def spectrum_matrix(params: CavityParams, instruments: Instruments, dtype=torch.float64, device=None) -> torch.Tensor:
    """M (bins, n) with S = M @ (|fft u|^2 + |fft v|^2) (FFT order): each grid mode's power
    P dw, spread by the Gaussian response, then the share of each bin (exact overlaps of the
    mode's cell [w - dw/2, w + dw/2] with the bin)."""
    n, dw = params.n, 2 * math.pi / params.T
    w = params.wavenumbers(dtype=torch.float64)  # FFT order
    power_per_mode = params.dt**2 / (2 * math.pi) * dw  # P dw per unit |fft|^2
    sigma = instruments.resolution / (2 * math.sqrt(2 * math.log(2)))
    # the response spreads each mode over fine points of the w axis, 8 per cell, out to 4 sigma
    half = math.ceil((4 * sigma + dw) / (dw / 8))
    fine = torch.arange(-half, half + 1, dtype=torch.float64) * (dw / 8)  # symmetric: a narrow response stays on the mode
    kernel = torch.exp(-0.5 * (fine / sigma) ** 2)
    kernel = kernel / kernel.sum()
    points = w[:, None] + fine[None, :]  # (n, f) where mode k's power lands
    weights = kernel.expand(n, -1)
    edges = torch.linspace(-instruments.spectrum_span / 2, instruments.spectrum_span / 2, instruments.spectrum_bins + 1,
                           dtype=torch.float64)
    # each fine point carries its weight over a cell of width dw / 8: share of that cell in each bin
    lo, hi = points - dw / 16, points + dw / 16
    overlap = (torch.minimum(hi[None], edges[1:, None, None]) - torch.maximum(lo[None], edges[:-1, None, None])).clamp_min(0)
    share = overlap / (dw / 8)  # (bins, n, f)
    M = power_per_mode * (share * weights[None]).sum(-1)
    return M.to(dtype=dtype, device=device)


def measure(u: torch.Tensor, v: torch.Tensor, params: CavityParams, instruments: Instruments,
            matrix: torch.Tensor | None = None, generator: torch.Generator | None = None) -> Measurement:
    """The instruments' readings of fields u, v (B, n) (module docstring); noise from
    ``generator``. ``matrix``: ``spectrum_matrix`` (computed here if None)."""
    real = u.real.dtype
    if matrix is None:
        matrix = spectrum_matrix(params, instruments, dtype=real, device=u.device)
    U, V = torch.fft.fft(u), torch.fft.fft(v)
    modes = U.real.square() + U.imag.square() + V.real.square() + V.imag.square()
    S = modes @ matrix.to(real).T
    intensity = u.real.square() + u.imag.square() + v.real.square() + v.imag.square()
    W = trapezoid_energy(intensity, params.dt)
    B, dev = u.shape[0], u.device

    def normal(*shape):  # drawn where the generator lives
        where = generator.device if generator is not None else dev
        return torch.randn(shape, generator=generator, dtype=real, device=where).to(dev)

    i = instruments
    if i.spectrum_noise:
        S = S * (1 + i.spectrum_noise * normal(B, i.spectrum_bins))
    S = S.clamp_min(0)
    if i.spectrum_floor:
        S = S + i.spectrum_floor * normal(B, i.spectrum_bins).abs()
    if i.energy_noise:
        W = (W * (1 + i.energy_noise * normal(B))).clamp_min(0)
    ac = None
    if i.autocorrelation_points:
        F = torch.fft.fft(intensity)
        circ = torch.fft.ifft(F.real.square() + F.imag.square()).real  # circular, delay k dt in FFT order
        circ = circ / circ[:, :1].clamp_min(torch.finfo(real).tiny)
        delays = torch.linspace(-i.autocorrelation_span / 2, i.autocorrelation_span / 2, i.autocorrelation_points,
                                dtype=torch.float64) / params.dt
        below = torch.floor(delays)
        frac = (delays - below).to(device=dev, dtype=real)
        k0 = torch.remainder(below.long(), params.n).to(dev)
        k1 = torch.remainder(below.long() + 1, params.n).to(dev)
        ac = circ[:, k0] * (1 - frac) + circ[:, k1] * frac
        if i.autocorrelation_noise:
            ac = ac + i.autocorrelation_noise * normal(B, i.autocorrelation_points)
    return Measurement(spectrum=S, energy=W, autocorrelation=ac)


def measured_reward(m: Measurement, reward: str = "autocorrelation") -> torch.Tensor:
    """r = sqrt(W) / M4 from the readings (module docstring), (B,); readings without spread
    give M4 = inf, hence r = 0."""
    if reward == "autocorrelation":
        if m.autocorrelation is None:
            raise ValueError("the autocorrelation reward needs the autocorrelator's readings")
        s = torch.fft.fft(m.autocorrelation).abs().sqrt()
    else:
        s = m.spectrum.clamp_min(0).sqrt()
    return m.energy.clamp_min(0).sqrt() / kurtosis(s)
