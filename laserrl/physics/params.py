"""Cavity parameters of the dimensionless coupled-NLS laser model.

Symbols follow the paper (Sun, Kaiser, Brunton, Kutz 2020, eqs. 6-8):

    i u_z + (D/2) u_tt - K u + (|u|^2 + A|v|^2) u + B v^2 u* = i R u
    i v_z + (D/2) v_tt + K v + (A|u|^2 + |v|^2) v + B u^2 v* = i R v
    R = 2 g0 (1 + tau d_tt) / (1 + E/E0) - Gamma,  E = int (|u|^2 + |v|^2) dt

The birefringence K is not a parameter here: it is the (batched) disturbance and
is passed to the physics functions next to the fields.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch


#: Integrators of the propagation over z (see ``CavityParams.integrator``).
INTEGRATORS = ("split", "dop853")


@dataclass(frozen=True)
class CavityParams:
    """Physical constants, grid and integrator resolution of the cavity.

    Attributes:
        D: average group-velocity dispersion (dimensionless; negative = anomalous).
        E0: saturation energy e_0 of the gain medium.
        tau: gain bandwidth parameter (gain filter 1 - tau k^2 in Fourier space).
        g0: pumping strength.
        Gamma: linear cavity loss.
        A: cross-phase modulation coefficient (2/3 for silica).
        B: four-wave mixing coefficient (1/3 for silica).
        Z: propagation length of one round trip (z in [0, Z]).
        T: width of the periodic time window, t in [-T/2, T/2).
        n: number of time samples (a power of two >= 16).
        z_steps: fixed integrator steps per round trip (numerical resolution, not
            physics): the steps of DOP853, or half the steps of the fine split-step pass.
            The default meets a relative L2 error <= 1e-4 per round trip against the
            DOP853 reference; see ``CavityParams.precise()``.
        z_steps_coarse: steps of the coarse split-step pass, 1 .. 2 z_steps - 1; None
            (default): ``min(ceil(5 z_steps / 4), 2 z_steps - 1)``, 10 at z_steps = 8
            (``split_passes``). z_steps_coarse = z_steps is the classic (N, 2N) pair.
            Only for ``integrator="split"``.
        integrator: "split" (default): Strang splitting into exact linear and Kerr
            flows, a coarse and a fine pass of ``split_passes`` steps (10 and 16 by
            default), Richardson-extrapolated to fourth order; needs A + B = 1, for which
            the Kerr flow is exact. "dop853": the 12-stage Dormand-Prince Runge-Kutta
            method in the interaction picture, z_steps steps; any A, B; used by
            ``precise()``.
    """

    D: float = -0.4
    E0: float = 4.23
    tau: float = 0.1
    g0: float = 1.73
    Gamma: float = 0.1
    A: float = 2.0 / 3.0
    B: float = 1.0 / 3.0
    Z: float = 1.5
    T: float = 60.0
    n: int = 256
    z_steps: int = 8
    z_steps_coarse: int | None = None
    integrator: str = "split"

    def __post_init__(self) -> None:
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"CavityParams.integrator must be one of {INTEGRATORS}, got {self.integrator!r}")
        for f in dataclasses.fields(self):
            if f.name == "integrator" or (f.name == "z_steps_coarse" and self.z_steps_coarse is None):
                continue
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"CavityParams.{f.name} must be a number, got {value!r}")
            if math.isnan(value) or math.isinf(value):
                raise ValueError(f"CavityParams.{f.name} must be finite, got {value!r}")
        for name in ("n", "z_steps", "z_steps_coarse"):  # whole numbers may arrive as floats from config files
            value = getattr(self, name)
            if isinstance(value, float) and value.is_integer():
                object.__setattr__(self, name, int(value))
        n = self.n
        if int(n) != n or n < 16 or (int(n) & (int(n) - 1)) != 0:
            raise ValueError(f"CavityParams.n must be a power of two >= 16, got {n!r}")
        for name in ("T", "Z", "E0"):
            if getattr(self, name) <= 0:
                raise ValueError(f"CavityParams.{name} must be > 0, got {getattr(self, name)!r}")
        if self.tau < 0:
            raise ValueError(f"CavityParams.tau must be >= 0, got {self.tau!r}")
        if self.Gamma < 0:
            raise ValueError(f"CavityParams.Gamma must be >= 0, got {self.Gamma!r}")
        if self.g0 < 0:
            raise ValueError(f"CavityParams.g0 must be >= 0, got {self.g0!r}")
        if int(self.z_steps) != self.z_steps or self.z_steps < 1:
            raise ValueError(f"CavityParams.z_steps must be a positive integer, got {self.z_steps!r}")
        if self.z_steps_coarse is not None:
            c = self.z_steps_coarse
            if self.integrator != "split":
                raise ValueError(f"CavityParams.z_steps_coarse applies to integrator='split' only, got {c!r} with "
                                 f"integrator={self.integrator!r}")
            if int(c) != c or not 1 <= c < 2 * self.z_steps:
                raise ValueError(f"CavityParams.z_steps_coarse must be an integer in [1, 2 z_steps - 1] = "
                                 f"[1, {2 * self.z_steps - 1}] (the fine pass has 2 z_steps steps), got {c!r}")
        if self.integrator == "split" and abs(self.A + self.B - 1.0) > 1e-9:
            raise ValueError(
                f"CavityParams.integrator='split' needs A + B = 1 (exact Kerr flow), got A={self.A!r}, "
                f"B={self.B!r}; use integrator='dop853' for other values")

    @classmethod
    def precise(cls, **overrides) -> "CavityParams":
        """Resolution for reference-grade accuracy: use with complex128 fields.

        Meets a relative L2 error <= 1e-8 per round trip against the DOP853
        reference solutions (``tests/physics/test_accuracy.py``): 32 steps of DOP853.
        """
        overrides.setdefault("integrator", "dop853")
        overrides.setdefault("z_steps", 32)
        return cls(**overrides)

    def replace(self, **changes) -> "CavityParams":
        return dataclasses.replace(self, **changes)

    @property
    def split_passes(self) -> tuple[int, int]:
        """(coarse, fine) Strang steps of the split-step integrator's two passes.

        The fine pass has 2 z_steps steps, the coarse pass ``z_steps_coarse`` or by default
        ceil(5 z_steps / 4) (10 and 16 at z_steps = 8). Richardson extrapolation of N1 and
        N2 steps leaves about d Z^4 / (N1 N2)^2 of a Strang error c h^2 + d h^4 at a cost of
        N1 + N2 stages: (10, 16) costs 2 stages more than (8, 16) and leaves 0.64x its error
        (``laserrl.physics.split_step``)."""
        fine = 2 * self.z_steps
        if self.z_steps_coarse is not None:
            return self.z_steps_coarse, fine
        return min(math.ceil(5 * self.z_steps / 4), fine - 1), fine

    def refined(self, factor: int) -> "CavityParams":
        """The same integrator with ``factor`` times the steps in every pass."""
        coarse = None if self.z_steps_coarse is None else self.z_steps_coarse * factor
        return self.replace(z_steps=self.z_steps * factor, z_steps_coarse=coarse)

    # --- grid -------------------------------------------------------------------
    @property
    def dt(self) -> float:
        return self.T / self.n

    def time_grid(self, dtype=torch.float64, device=None) -> torch.Tensor:
        """t = linspace(-T/2, T/2, n+1)[:n]."""
        return torch.linspace(-self.T / 2, self.T / 2, self.n + 1, dtype=dtype, device=device)[: self.n]

    def wavenumbers(self, dtype=torch.float64, device=None) -> torch.Tensor:
        """k = 2 pi / T * fftfreq(n, 1/n), in FFT order."""
        return (2 * math.pi / self.T) * torch.fft.fftfreq(self.n, 1.0 / self.n, dtype=dtype, device=device)
