"""Reference solver: one cavity, scipy DOP853 per round trip, numpy only.

This is the slow, trusted path the batched torch solver is tested and benchmarked
against. It integrates the same Fourier-space ODE as ``laserrl.physics.cavity``:

    d/dz u^ = (-i D k^2/2 - i K - Gamma) u^ + g(E) (1 - tau k^2) u^ + F[ i(|u|^2 + A|v|^2) u + i B v^2 u* ]
    d/dz v^ = (-i D k^2/2 + i K - Gamma) v^ + g(E) (1 - tau k^2) v^ + F[ i(A|u|^2 + |v|^2) v + i B u^2 v* ]
    g(E) = 2 g0 / (1 + E/E0),  E = trapezoid(|u|^2 + |v|^2, t)

then applies J1 JP J2 J3. The integrator is the one the paper's public code calls:
Hairer's Fortran DOP853 through ``scipy.integrate.ode`` ("dop853"), restarted every
round trip. That code sets no tolerances, so it runs at that integrator's defaults,
``PAPER_RTOL`` = 1e-6 and ``PAPER_ATOL`` = 1e-12, which are also the defaults here.
(At ``solve_ivp``'s looser defaults, rtol 1e-3 and atol 1e-6, it is 3.5e-5 instead of
1.3e-9 from the stored high-accuracy solutions.)
"""
from __future__ import annotations

import numpy as np
from scipy.integrate import ode

from laserrl.physics.params import CavityParams


#: Tolerances of the paper's public code: ``scipy.integrate.ode``'s "dop853" defaults.
PAPER_RTOL, PAPER_ATOL = 1e-6, 1e-12

#: Steps per round trip at most (``ode``'s own default, 500, is too few for rtol 1e-10).
MAX_STEPS = 1_000_000


def grid(params: CavityParams) -> tuple[np.ndarray, np.ndarray]:
    """(t, k) as numpy float64 arrays."""
    t = np.linspace(-params.T / 2, params.T / 2, params.n + 1)[: params.n]
    k = 2 * np.pi / params.T * np.fft.fftfreq(params.n, 1.0 / params.n)
    return t, k


def trapezoid_energy(u: np.ndarray, v: np.ndarray, dt: float) -> float:
    """E = trapezoid(|u|^2 + |v|^2, t) over the n samples (not a periodic sum)."""
    p = np.abs(u) ** 2 + np.abs(v) ** 2
    return float(dt * (p.sum() - 0.5 * (p[0] + p[-1])))


def jones_matrix(angles_rad: np.ndarray) -> np.ndarray:
    """J1 @ JP @ J2 @ J3 for angles (alpha1, alpha2, alpha3, alpha_p) in radians."""

    def rot(a):
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    quarter = np.diag([np.exp(-1j * np.pi / 4), np.exp(1j * np.pi / 4)])
    half = np.diag([-1j, 1j])
    pol = np.diag([1.0 + 0j, 0.0])
    a1, a2, a3, ap = angles_rad
    j1 = rot(a1) @ quarter @ rot(-a1)
    j2 = rot(a2) @ quarter @ rot(-a2)
    j3 = rot(a3) @ half @ rot(-a3)
    jp = rot(ap) @ pol @ rot(-ap)
    return j1 @ jp @ j2 @ j3


def propagate(u, v, K, params: CavityParams, rtol=PAPER_RTOL, atol=PAPER_ATOL):
    """Integrate the coupled NLS over z in [0, Z] (no Jones matrices)."""
    n = params.n
    _, k = grid(params)
    dt = params.dt
    lin_common = -0.5j * params.D * k**2 - params.Gamma
    lin_u = lin_common - 1j * K
    lin_v = lin_common + 1j * K
    gain_shape = 1.0 - params.tau * k**2
    A, B = params.A, params.B

    def rhs(_z, y):
        uh = y[:n] + 1j * y[n : 2 * n]
        vh = y[2 * n : 3 * n] + 1j * y[3 * n :]
        ut = np.fft.ifft(uh)
        vt = np.fft.ifft(vh)
        g = 2 * params.g0 / (1 + trapezoid_energy(ut, vt, dt) / params.E0)
        au, av = np.abs(ut) ** 2, np.abs(vt) ** 2
        nu = 1j * ((au + A * av) * ut + B * vt**2 * np.conj(ut))
        nv = 1j * ((A * au + av) * vt + B * ut**2 * np.conj(vt))
        du = (lin_u + g * gain_shape) * uh + np.fft.fft(nu)
        dv = (lin_v + g * gain_shape) * vh + np.fft.fft(nv)
        return np.concatenate([du.real, du.imag, dv.real, dv.imag])

    uh0, vh0 = np.fft.fft(u), np.fft.fft(v)
    y0 = np.concatenate([uh0.real, uh0.imag, vh0.real, vh0.imag])
    solver = ode(rhs).set_integrator("dop853", rtol=rtol, atol=atol, nsteps=MAX_STEPS)
    solver.set_initial_value(y0, 0.0)
    y = solver.integrate(params.Z)
    if not solver.successful():
        raise RuntimeError(f"DOP853 failed with return code {solver.get_return_code()}")
    uh = y[:n] + 1j * y[n : 2 * n]
    vh = y[2 * n : 3 * n] + 1j * y[3 * n :]
    return np.fft.ifft(uh), np.fft.ifft(vh)


def round_trip(u, v, angles_rad, K, params: CavityParams, rtol=PAPER_RTOL, atol=PAPER_ATOL):
    """One round trip of one cavity: propagate, then apply J1 JP J2 J3."""
    u, v = propagate(np.asarray(u, complex), np.asarray(v, complex), float(K), params, rtol, atol)
    m = jones_matrix(np.asarray(angles_rad, float))
    return m[0, 0] * u + m[0, 1] * v, m[1, 0] * u + m[1, 1] * v


def reward_terms(u, v, params: CavityParams) -> tuple[float, float, float]:
    """(E, M4, r) of one field pair, as in ``laserrl.physics.reward_terms``."""
    phi2 = np.abs(u) ** 2 + np.abs(v) ** 2
    energy = np.sqrt(params.dt * (phi2.sum() - 0.5 * (phi2[0] + phi2[-1])))
    s = np.abs(np.fft.fft(np.sqrt(phi2)))
    m4 = np.mean((s - s.mean()) ** 4) / np.std(s) ** 4
    return float(energy), float(m4), float(energy / m4)
