"""Reward landscapes r = E / M4 over one waveplate angle (and over a grid of two), swept
upwards and downwards with the cavity state carried over from each angle to the next.

A bistable cavity has two stable states (a mode-locked pulse and a plane wave) at the
same angles; which one it is in depends on where it came from. Sweeping an angle up and
down and comparing the two rewards at each angle shows where that is the case: the
intervals where the sweeps disagree are the hysteresis of the paper's fig. 4(a).

Each move to the next angle is one *agent step* of the environment
(``laserrl.envs.step.step_cavity``, the function the env steps with), with the env's numerics
(``StepSettings.from_task``): so the landscape is the one an agent turning the plate one
step at a time sees.

All rows of a grid and both sweep directions run as one batch of cavities.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch

from laserrl.envs.laser_env import ANGLE_NAMES, LaserTask
from laserrl.envs.step import CavityState, StepNumerics, _positive_int, step_cavity
from laserrl.physics import CavityParams, sech_fields

_DTYPES = {"complex64": torch.complex64, "complex128": torch.complex128}


@dataclass(frozen=True)
class StepSettings:
    """Numerics of one agent step (as in the env) and of settling a cavity from its initial fields.

    Attributes:
        max_round_trips: round trips per agent step at most (env: 30).
        tol: convergence tolerance per step (env: 1e-5 in complex64).
        dtype: complex dtype of the fields.
        compile: ``torch.compile`` the round trip.
        min_round_trips: round trips per step at least (env: 2; see ``laserrl.envs.step``).
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
        _positive_int(self.settle_round_trips, "settle_round_trips")
        self.step  # StepNumerics validates the rest

    @property
    def step(self) -> StepNumerics:
        """The numerics of one agent step."""
        return StepNumerics(self.max_round_trips, self.tol, self.min_round_trips, self.compile)

    @property
    def settle(self) -> StepNumerics:
        """The numerics of settling at fixed angles: up to ``settle_round_trips``."""
        return StepNumerics(self.settle_round_trips, self.tol, min(self.min_round_trips, self.settle_round_trips),
                            self.compile)

    @classmethod
    def from_task(cls, task: LaserTask, **changes) -> "StepSettings":
        """The env's per-step numerics of ``task`` (max and min round trips, tol, dtype, compile)."""
        kwargs = dict(max_round_trips=task.max_round_trips, min_round_trips=task.min_round_trips, tol=task.tol,
                      dtype=_DTYPES[task.dtype], compile=task.compile)
        kwargs.update(changes)
        return cls(**kwargs)


def initial_state(u, v, angles, K) -> CavityState:
    """A ``CavityState`` of B cavities from fields (B, n), angles (B, 4) radians and K (B,) or a number."""
    B = u.shape[0]
    K = torch.as_tensor(K, dtype=torch.float64, device=u.device).expand(B).clone()
    return CavityState(u=u, v=v, angles=angles.to(torch.float64), K=K,
                       step_count=torch.zeros(B, dtype=torch.int64, device=u.device), batch_size=[B])


def settle(u, v, angles, K, params: CavityParams, settings: StepSettings):
    """Run cavities at fixed ``angles`` until converged or ``settings.settle_round_trips``
    (at least ``min_round_trips``). Returns (u, v, r, converged)."""
    state, out = step_cavity(initial_state(u, v, angles, K), angles, params, settings.settle)
    return state.u, state.v, out.r, out.converged


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
    (``laserrl.envs.step.step_cavity``). Rows (``base_deg`` (R, 4), the swept entry ignored) and the two
    directions run as one batch of 2R cavities.
    """
    if angle not in ANGLE_NAMES:
        raise ValueError(f"angle must be one of {ANGLE_NAMES}, got {angle!r}")
    values = _values(values_deg)
    base = _rows(base_deg)
    R, n, ia = base.shape[0], values.numel(), ANGLE_NAMES.index(angle)
    angles = base.repeat(2, 1)  # rows 0..R-1 sweep up, R..2R-1 sweep down
    u, v = sech_fields(2 * R, params, dtype=settings.dtype)
    state = initial_state(u, v, torch.deg2rad(angles), float(K))
    r_up, r_down = torch.zeros(R, n, dtype=torch.float64), torch.zeros(R, n, dtype=torch.float64)
    rt_up, rt_down = torch.zeros(R, n, dtype=torch.int64), torch.zeros(R, n, dtype=torch.int64)
    for i in range(n):
        angles[:R, ia] = values[i]
        angles[R:, ia] = values[n - 1 - i]
        # the first angle settles the initial fields, each next one is an agent step
        state, out = step_cavity(state, torch.deg2rad(angles), params, settings.settle if i == 0 else settings.step)
        r, rts = out.r.double(), out.round_trips
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
    return settle(u, v, torch.deg2rad(angles.reshape(R * n, 4)), float(K), params, settings)[2].double().reshape(R, n)
