"""Extremum-seeking control (ESC) of any subset of the four angles, batched over cavities.

Discrete time, one sample per agent step k (as in the paper's section 4, with the
cavity's r = E / M4 as the objective J). For each controlled angle j with estimate
theta_j, dither amplitude a_j (deg) and dither frequency f_j (cycles per step):

    command      theta_j + a_j sin(2 pi f_j k)
    high-pass    rho_k = HPF(J_k)                    removes the slowly varying mean of J
    demodulate   xi_jk = rho_k sin(2 pi f_j k - phi)  mean (a_j / 2) dJ/dtheta_j
    low-pass     xi_jk <- LPF(xi_jk)                 optional; removes the 2 f_j ripple
    integrate    theta_j += clip(gain_j (2 / a_j) xi_jk, +-max_step_deg)

J_k is the r measured after the step with the command of step k. The filters are
Butterworth filters from ``scipy.signal.butter`` (fs = 1 per step). Distinct dither
frequencies separate the angles: the demodulated cross terms average out. ESC climbs the
local gradient only: from a state that is not mode-locked (flat r) it does not find a lock.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np
import torch

from laserrl.control.checks import is_finite_number as _finite
from laserrl.control.filters import StepFilter
from laserrl.envs.laser_env import ANGLE_NAMES


def observed_r(obs) -> np.ndarray:
    """The reward a controller reads (B,), float64 numpy, from a plant observation: the
    instruments' ``r_measured`` where the observation is measured (an experiment has no other),
    else the paper's ``r``."""
    key = "r_measured" if "r_measured" in obs.keys() else "r"
    return obs[key].reshape(-1).detach().cpu().numpy().astype(np.float64)


def per_angle(value, controlled, name: str) -> np.ndarray:
    """One float per controlled angle from a number (all angles) or a {angle: value} mapping."""
    if isinstance(value, Mapping):
        missing = [a for a in controlled if a not in value]
        unknown = [a for a in value if a not in ANGLE_NAMES]
        if unknown:
            raise ValueError(f"{name}: unknown angle(s) {unknown}; choose from {ANGLE_NAMES}")
        if missing:
            raise ValueError(f"{name} needs a value for every controlled angle, missing {missing}")
        out = [value[a] for a in controlled]
    else:
        out = [value] * len(controlled)
    for x in out:
        if not _finite(x):
            raise ValueError(f"{name} must be finite numbers, got {value!r}")
    return np.asarray(out, dtype=np.float64)


@dataclass
class ESCParams:
    """ESC settings; angles in degrees, frequencies in cycles per agent step (Nyquist 0.5).

    ``amplitude_deg``, ``gain`` and ``frequency`` take a number or one value per angle
    name ({alpha1: ..., alpha2: ...}); ``frequency`` must differ between controlled angles.
    """

    amplitude_deg: Any = 1.0
    frequency: Any = field(default_factory=lambda: {"alpha1": 0.125, "alpha2": 0.1, "alpha3": 0.15, "alpha_p": 0.175})
    gain: Any = 150.0 # deg^2 per step per unit of r: the step is gain x (estimated dr/dtheta in 1/deg)
    highpass_cutoff: float = 0.05  # cycles per step
    lowpass_cutoff: float | None = 0.05  # cycles per step; None: no low-pass
    filter_order: int = 1
    phase_deg: float = 0.0  # demodulation phase lag
    max_step_deg: float = 1.0  # largest change of an estimate in one step

    def resolve(self, controlled) -> dict:
        """Check the values for these controlled angles; returns per-angle arrays (m,)."""
        a = per_angle(self.amplitude_deg, controlled, "amplitude_deg")
        f = per_angle(self.frequency, controlled, "frequency")
        g = per_angle(self.gain, controlled, "gain")
        if (a <= 0).any():
            raise ValueError(f"amplitude_deg must be > 0, got {self.amplitude_deg!r}")
        if ((f <= 0) | (f >= 0.5)).any():
            raise ValueError(f"frequency must lie in (0, 0.5) cycles per step, got {self.frequency!r}")
        if len(set(f.tolist())) != len(f):
            raise ValueError(f"frequency must differ between the controlled angles {list(controlled)}, got {f.tolist()}")
        if (g < 0).any():
            raise ValueError(f"gain must be >= 0, got {self.gain!r}")
        for name in ("highpass_cutoff", "lowpass_cutoff"):
            c = getattr(self, name)
            if c is None and name == "lowpass_cutoff":
                continue
            if isinstance(c, bool) or not isinstance(c, (int, float)) or not 0 < c < 0.5:
                raise ValueError(f"{name} must lie in (0, 0.5) cycles per step, got {c!r}")
        if isinstance(self.filter_order, bool) or int(self.filter_order) != self.filter_order or not 1 <= self.filter_order <= 8:
            raise ValueError(f"filter_order must be an integer in [1, 8], got {self.filter_order!r}")
        if not (_finite(self.max_step_deg) and self.max_step_deg > 0):
            raise ValueError(f"max_step_deg must be > 0, got {self.max_step_deg!r}")
        if not _finite(self.phase_deg):
            raise ValueError(f"phase_deg must be finite, got {self.phase_deg!r}")
        return {"amplitude": a, "frequency": f, "gain": g}


class ExtremumSeeking:
    """Batched ESC on the angles ``controlled`` of B cavities (see the module docstring).

    ``reset(obs, angles_deg, mask)`` (re)starts the cavities in ``mask`` at their current
    angles; ``act(obs, angles_deg)`` takes the observation (its ``r``) that the last command
    produced and returns the next command (B, 4) in degrees.
    """

    name = "esc"

    def __init__(self, params: ESCParams, controlled, num_cavities: int):
        self.params = params
        self.idx = [ANGLE_NAMES.index(a) for a in controlled]
        v = params.resolve(controlled)
        self.a, self.f, self.gain = v["amplitude"], v["frequency"], v["gain"]
        B, m = num_cavities, len(self.idx)
        self.hpf = StepFilter("high", params.highpass_cutoff, params.filter_order, (B,))
        self.lpf = StepFilter("low", params.lowpass_cutoff, params.filter_order, (B, m)) if params.lowpass_cutoff else None
        self.theta = np.zeros((B, m))  # estimates (deg)
        self.k = np.zeros(B, dtype=np.int64)  # dither clock per cavity, 0 = just (re)started
        self.grad = np.zeros((B, m))  # last gradient estimate dr/dtheta (1/deg), for diagnostics

    def reset(self, obs, angles_deg: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        theta = angles_deg[:, self.idx].detach().cpu().numpy().astype(np.float64)
        m = np.ones(len(theta), dtype=bool) if mask is None else mask.detach().cpu().numpy().astype(bool)
        self.theta = np.where(m[:, None], theta, self.theta)
        self.k = np.where(m, 0, self.k)
        self.grad = np.where(m[:, None], 0.0, self.grad)

    def _dither(self, k: np.ndarray, lag_deg: float = 0.0) -> np.ndarray:
        return np.sin(2 * np.pi * self.f[None, :] * k[:, None] - np.deg2rad(lag_deg))

    def act(self, obs, angles_deg: torch.Tensor) -> torch.Tensor:
        r = observed_r(obs)
        # k = 1: r answers ESC's first command (the estimate itself, dither sin 0 = 0). The filters
        # start in the steady state of that r, so that a step from the r before ESC (e.g. that
        # of the initial fields) is no false gradient
        fresh = self.k <= 1
        if fresh.any():
            self.hpf.reset(r, fresh)
            if self.lpf is not None:
                self.lpf.reset(np.zeros_like(self.theta), fresh)
        rho = self.hpf(r)
        started = self.k > 0  # r answers the command of step k - 1; none yet right after a (re)start
        xi = rho[:, None] * self._dither(self.k - 1, self.params.phase_deg)
        if self.lpf is not None:
            xi = self.lpf(xi)
        self.grad = np.where(started[:, None], xi * 2.0 / self.a, 0.0)
        step = np.clip(self.gain * self.grad, -self.params.max_step_deg, self.params.max_step_deg)
        self.theta = self.theta + step
        command = angles_deg.clone().to(torch.float64)
        command[:, self.idx] = torch.as_tensor(self.theta + self.a * self._dither(self.k), dtype=torch.float64,
                                               device=angles_deg.device)
        self.k = self.k + 1
        return command
