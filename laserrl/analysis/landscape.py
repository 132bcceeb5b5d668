"""Reward landscapes r = E / M4 over one waveplate angle (and over a grid of two), swept
upwards and downwards with the cavity state carried over from each angle to the next.

A bistable cavity has two stable states (a mode-locked pulse and a plane wave) at the
same angles; which one it is in depends on where it came from. Sweeping an angle up and
down and comparing the two rewards at each angle shows where that is the case: the
intervals where the sweeps disagree are the hysteresis of the paper's fig. 4(a).

Each move to the next angle is one *agent step* of the environment (``LaserCavityEnv``):
at most ``max_round_trips`` round trips, stopping when the change of
phi = sqrt(|u|^2 + |v|^2) between round trips falls below ``tol``. So the landscape is the
one an agent turning the plate one step at a time sees, with the env's numerics
(``StepSettings.from_task``). One difference, ``min_round_trips``: J1 (alpha1) is the
last, unitary element of the round trip, so the first round trip after a change of
alpha1 alone leaves phi unchanged and the convergence check stops a converged cavity
after that one round trip; the change then only acts in the next agent step. The env
has this one-step lag; the sweeps force ``min_round_trips = 2`` round trips per step
(the default), so that every angle acts in its own step.

All rows of a grid and both sweep directions run as one batch of cavities.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import torch

from laserrl.envs.laser_env import ANGLE_NAMES, LaserTask
from laserrl.physics import CavityParams, reward_terms, round_trip, run_to_convergence, sech_fields

_DTYPES = {"complex64": torch.complex64, "complex128": torch.complex128}


@dataclass(frozen=True)
class StepSettings:
    """Numerics of one agent step (as in the env) and of settling a cavity from its initial fields.

    Attributes:
        max_round_trips: round trips per agent step at most (env: 30).
        tol: convergence tolerance per step (env: 1e-5 in complex64).
        dtype: complex dtype of the fields.
        compile: ``torch.compile`` the round trip.
        min_round_trips: round trips per step at least (see the module docstring; the env: 1).
        settle_round_trips: round trips at most to settle the initial fields at the first
            angle of a sweep, and of a cold start (paper: 500 per step).
    """

    max_round_trips: int = 30
    tol: float = 1e-5
    dtype: torch.dtype = torch.complex64
    compile: bool = False
    min_round_trips: int = 2
    settle_round_trips: int = 500

    def __post_init__(self):
        for name in ("max_round_trips", "min_round_trips", "settle_round_trips"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or int(value) != value or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if self.min_round_trips > self.max_round_trips:
            raise ValueError(f"min_round_trips ({self.min_round_trips}) must be <= max_round_trips ({self.max_round_trips})")

    @classmethod
    def from_task(cls, task: LaserTask, **changes) -> "StepSettings":
        """The env's per-step numerics of ``task`` (max_round_trips, tol, dtype, compile)."""
        kwargs = dict(max_round_trips=task.max_round_trips, tol=task.tol, dtype=_DTYPES[task.dtype], compile=task.compile)
        kwargs.update(changes)
        return cls(**kwargs)


def agent_step(u, v, angles, K, params: CavityParams, settings: StepSettings):
    """The cavity after one agent step at ``angles`` (B, 4) radians: ``settings.min_round_trips``
    round trips, then more until converged or ``max_round_trips`` in all. Returns (u, v, round trips)."""
    forced = settings.min_round_trips - 1
    for _ in range(forced):
        u, v = round_trip(u, v, angles, K, params, compile=settings.compile)
    res = run_to_convergence(u, v, angles, K, params, tol=settings.tol,
                             max_round_trips=settings.max_round_trips - forced, compile=settings.compile)
    return res.u, res.v, res.round_trips + forced


def settle(u, v, angles, K, params: CavityParams, settings: StepSettings):
    """Run cavities at fixed ``angles`` until converged or ``settings.settle_round_trips``
    (at least ``min_round_trips``). Returns (u, v, r, converged)."""
    forced = min(settings.min_round_trips, settings.settle_round_trips) - 1
    for _ in range(forced):
        u, v = round_trip(u, v, angles, K, params, compile=settings.compile)
    res = run_to_convergence(u, v, angles, K, params, tol=settings.tol,
                             max_round_trips=settings.settle_round_trips - forced, compile=settings.compile)
    return res.u, res.v, reward_terms(res.u, res.v, params)[2], res.converged


def _values(values_deg, name: str = "values_deg") -> torch.Tensor:
    values = torch.as_tensor(values_deg, dtype=torch.float64).flatten()
    if values.numel() < 2:
        raise ValueError(f"{name} needs at least two angles, got {values.tolist()}")
    if not bool(torch.isfinite(values).all()) or not bool((values.diff() > 0).all()):
        raise ValueError(f"{name} must be finite and strictly increasing, got {values.tolist()}")
    return values


def _rows(base_deg) -> torch.Tensor:
    base = torch.as_tensor(base_deg, dtype=torch.float64)
    base = base[None] if base.ndim == 1 else base
    if base.ndim != 2 or base.shape[1] != 4 or not bool(torch.isfinite(base).all()):
        raise ValueError(f"base_deg must be finite angles (alpha1, alpha2, alpha3, alpha_p) of shape (4,) or (R, 4), "
                         f"got shape {tuple(base.shape)}")
    return base


@dataclass
class Sweep:
    """Rewards along one angle, reached sweeping upwards and downwards, for R rows of the
    other angles. ``r_up[i, j]`` and ``r_down[i, j]`` are both at ``values_deg[j]``."""

    angle: str
    values_deg: torch.Tensor  # (n,) ascending
    base_deg: torch.Tensor  # (R, 4) the angles of each row (the swept one is replaced)
    K: float
    r_up: torch.Tensor  # (R, n)
    r_down: torch.Tensor  # (R, n)
    round_trips_up: torch.Tensor = field(repr=False)  # (R, n) round trips of each step
    round_trips_down: torch.Tensor = field(repr=False)

    @property
    def step_deg(self) -> float:
        """Grid spacing (the median, in case the grid is uneven)."""
        return float(self.values_deg.diff().median())

    def hysteresis(self, dr: float, row: int = 0) -> list[tuple[float, float]]:
        """Intervals [lo, hi] (deg) of grid angles where |r_up - r_down| > dr."""
        return intervals(self.values_deg, (self.r_up[row] - self.r_down[row]).abs() > dr)

    def locked(self, r_min: float, direction: str, row: int = 0) -> list[tuple[float, float]]:
        """Intervals of grid angles where the ``direction`` ("up" or "down") sweep has r >= r_min."""
        r = {"up": self.r_up, "down": self.r_down}[direction]
        return intervals(self.values_deg, r[row] >= r_min)

    def to_dict(self) -> dict:
        return {"angle": self.angle, "values_deg": self.values_deg.tolist(), "base_deg": self.base_deg.tolist(),
                "K": self.K, "r_up": self.r_up.tolist(), "r_down": self.r_down.tolist(),
                "round_trips_up": self.round_trips_up.tolist(), "round_trips_down": self.round_trips_down.tolist()}


def intervals(values_deg, mask) -> list[tuple[float, float]]:
    """Maximal runs of consecutive grid points where ``mask`` holds, as (first, last) angles."""
    values = torch.as_tensor(values_deg, dtype=torch.float64).flatten().tolist()
    flags = torch.as_tensor(mask).flatten().tolist()
    if len(values) != len(flags):
        raise ValueError(f"values_deg ({len(values)}) and mask ({len(flags)}) differ in length")
    out, start = [], None
    for j, flag in enumerate(flags + [False]):
        if flag and start is None:
            start = j
        elif not flag and start is not None:
            out.append((values[start], values[j - 1]))
            start = None
    return out


def interval_width(interval: tuple[float, float], step_deg: float) -> float:
    """Width of an interval of grid points, counting each point as a cell of ``step_deg``."""
    return interval[1] - interval[0] + step_deg


def sweep(angle: str, values_deg: Sequence[float], base_deg, K: float, params: CavityParams,
          settings: StepSettings) -> Sweep:
    """Sweep ``angle`` over ``values_deg`` upwards and downwards, carrying the state.

    Each sweep starts from the paper's sech fields at its first angle, settled for up to
    ``settings.settle_round_trips`` round trips; then each next angle is one agent step
    (``agent_step``). Rows (``base_deg`` (R, 4), the swept entry ignored) and the two
    directions run as one batch of 2R cavities.
    """
    if angle not in ANGLE_NAMES:
        raise ValueError(f"angle must be one of {ANGLE_NAMES}, got {angle!r}")
    values = _values(values_deg)
    base = _rows(base_deg)
    R, n, ia = base.shape[0], values.numel(), ANGLE_NAMES.index(angle)
    angles = base.repeat(2, 1)  # rows 0..R-1 sweep up, R..2R-1 sweep down
    u, v = sech_fields(2 * R, params, dtype=settings.dtype)
    r_up, r_down = torch.zeros(R, n, dtype=torch.float64), torch.zeros(R, n, dtype=torch.float64)
    rt_up, rt_down = torch.zeros(R, n, dtype=torch.int64), torch.zeros(R, n, dtype=torch.int64)
    Kb = torch.full((2 * R,), float(K), dtype=torch.float64)
    for i in range(n):
        angles[:R, ia] = values[i]
        angles[R:, ia] = values[n - 1 - i]
        rad = torch.deg2rad(angles)
        if i == 0:
            res = run_to_convergence(u, v, rad, Kb, params, tol=settings.tol, max_round_trips=settings.settle_round_trips,
                                     compile=settings.compile)
            u, v, rts = res.u, res.v, res.round_trips
        else:
            u, v, rts = agent_step(u, v, rad, Kb, params, settings)
        r = reward_terms(u, v, params)[2].double()
        r_up[:, i], r_down[:, n - 1 - i] = r[:R], r[R:]
        rt_up[:, i], rt_down[:, n - 1 - i] = rts[:R], rts[R:]
    return Sweep(angle, values, base.clone(), float(K), r_up, r_down, rt_up, rt_down)


def cold_landscape(angle: str, values_deg: Sequence[float], base_deg, K: float, params: CavityParams,
                   settings: StepSettings) -> torch.Tensor:
    """r at every grid angle from the sech fields, settled there for up to
    ``settings.settle_round_trips`` round trips (no history), (R, n); one batch of R n cavities."""
    if angle not in ANGLE_NAMES:
        raise ValueError(f"angle must be one of {ANGLE_NAMES}, got {angle!r}")
    values = _values(values_deg)
    base = _rows(base_deg)
    R, n = base.shape[0], values.numel()
    angles = base[:, None, :].repeat(1, n, 1)
    angles[:, :, ANGLE_NAMES.index(angle)] = values
    u, v = sech_fields(R * n, params, dtype=settings.dtype)
    res = run_to_convergence(u, v, torch.deg2rad(angles.reshape(R * n, 4)), float(K), params, tol=settings.tol,
                             max_round_trips=settings.settle_round_trips, compile=settings.compile)
    return reward_terms(res.u, res.v, params)[2].double().reshape(R, n)
