"""Scenarios: the birefringence K of every cavity over time, and where the cavities start.

K(t) at agent step t = 0 .. steps-1 (the value the cavity runs with during step t):

    K(t) = clip(K0 + drift(t) + sum of jumps up to t, bounds)

* ``K0``: one value for every cavity, or a list: cavity i starts at ``K0[i % len(K0)]`` (with
  no drift and no jumps, the fixed-K grid of ``laserrl-eval`` as one run of cavities).

* drift "none"; "random_walk": a Gaussian random walk with ``sigma`` per step, reflected at
  ``bounds`` (so it stays bounded); "sinusoid": ``amplitude`` sin(2 pi t / ``period`` + phase),
  phase uniform in [0, 2 pi) per cavity if ``random_phase``.
* jumps at the steps ``jumps.times``: K jumps to a value drawn uniformly from
  ``jumps.range`` (at least ``jumps.min_size`` away from the value before the jump), then
  drifts on from there.

Each cavity i draws its own trajectory from ``numpy.random.default_rng([seed, i])``, so a
cavity's trajectory does not depend on how many cavities run with it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from laserrl.control.checks import is_finite_number as _finite
from laserrl.envs.laser_env import ANGLE_NAMES


@dataclass
class Scenario:
    name: str = "constant"
    steps: int = 200
    K0: float | Sequence[float] = 0.1
    bounds: Sequence[float] = (0.0, 0.4)
    drift: Mapping[str, Any] = field(default_factory=lambda: {"kind": "none"})
    jumps: Mapping[str, Any] = field(default_factory=lambda: {"times": [], "range": [0.0, 0.4], "min_size": 0.0})
    init_angles_deg: Mapping[str, Any] = field(
        default_factory=lambda: {"alpha1": [-40.0, -10.0], "alpha2": 3.0, "alpha3": 28.0, "alpha_p": 88.0})
    init_fields: str = "sech"

    def __post_init__(self):
        if isinstance(self.steps, bool) or int(self.steps) != self.steps or self.steps < 1:
            raise ValueError(f"scenario.steps must be a positive integer, got {self.steps!r}")
        self.steps = int(self.steps)
        lo, hi = _pair(self.bounds, "scenario.bounds")
        self.bounds = (lo, hi)
        starts = [self.K0] if _finite(self.K0) else self.K0
        if isinstance(starts, (str, bytes)) or not isinstance(starts, Sequence) or not starts or \
                not all(_finite(k) and lo <= k <= hi for k in starts):
            raise ValueError(f"scenario.K0 must be a number or a non-empty list of numbers within scenario.bounds "
                             f"{list(self.bounds)}, got {self.K0!r}")
        self.K0 = float(self.K0) if _finite(self.K0) else [float(k) for k in starts]
        drift = {"kind": "none", **dict(self.drift)}
        kind = drift["kind"]
        if kind not in ("none", "random_walk", "sinusoid"):
            raise ValueError(f"scenario.drift.kind must be none, random_walk or sinusoid, got {kind!r}")
        if kind == "random_walk" and not (_finite(drift.get("sigma")) and drift["sigma"] >= 0):
            raise ValueError(f"scenario.drift.sigma must be >= 0, got {drift.get('sigma')!r}")
        if kind == "sinusoid":
            if not (_finite(drift.get("amplitude")) and drift["amplitude"] >= 0):
                raise ValueError(f"scenario.drift.amplitude must be >= 0, got {drift.get('amplitude')!r}")
            if not (_finite(drift.get("period")) and drift["period"] > 0):
                raise ValueError(f"scenario.drift.period must be > 0 steps, got {drift.get('period')!r}")
        self.drift = drift
        jumps = {"times": [], "range": list(self.bounds), "min_size": 0.0, **dict(self.jumps)}
        times = list(jumps["times"] or [])
        if any(isinstance(t, bool) or not isinstance(t, int) or not 0 < t < self.steps for t in times) or \
                times != sorted(set(times)):
            raise ValueError(f"scenario.jumps.times must be increasing integer steps in (0, {self.steps}), got {times!r}")
        jlo, jhi = _pair(jumps["range"], "scenario.jumps.range")
        if jlo < lo or jhi > hi:
            raise ValueError(f"scenario.jumps.range {[jlo, jhi]} must lie within scenario.bounds {list(self.bounds)}")
        if not (_finite(jumps["min_size"]) and 0 <= jumps["min_size"] <= jhi - jlo):
            raise ValueError(f"scenario.jumps.min_size must lie in [0, width of jumps.range], got {jumps['min_size']!r}")
        self.jumps = {"times": times, "range": (jlo, jhi), "min_size": float(jumps["min_size"])}
        init = dict(self.init_angles_deg)
        if set(init) != set(ANGLE_NAMES):
            raise ValueError(f"scenario.init_angles_deg must give all of {ANGLE_NAMES}, got {sorted(init)}")
        self.init_angles_deg = {a: _pair(init[a], f"scenario.init_angles_deg.{a}", allow_number=True) for a in ANGLE_NAMES}
        if self.init_fields not in ("sech", "noise"):
            raise ValueError(f"scenario.init_fields must be 'sech' or 'noise', got {self.init_fields!r}")

    def cavity_rng(self, seed: int, i: int) -> np.random.Generator:
        return np.random.default_rng([int(seed), int(i)])

    def start_K(self, i: int) -> float:
        """K0 of cavity i."""
        return self.K0 if isinstance(self.K0, float) else self.K0[i % len(self.K0)]

    def K_trajectory(self, rng: np.random.Generator, K0: float | None = None) -> np.ndarray:
        """K(t), t = 0 .. steps-1, of one cavity starting at ``K0`` (default: cavity 0's)."""
        lo, hi = self.bounds
        T, d = self.steps, self.drift
        K = np.empty(T)
        # draws in a fixed order (drift noise, phase, jumps) so that each part is reproducible
        noise = rng.standard_normal(T) * float(d.get("sigma", 0.0)) if d["kind"] == "random_walk" else np.zeros(T)
        phase = rng.uniform(0, 2 * np.pi) if d["kind"] == "sinusoid" and d.get("random_phase", True) else 0.0
        jump_draws = rng.random((len(self.jumps["times"]), 64))
        level, jumps = float(self.start_K(0) if K0 is None else K0), 0
        for t in range(T):
            if jumps < len(self.jumps["times"]) and t == self.jumps["times"][jumps]:
                level = self._jump_target(level, jump_draws[jumps])
                jumps += 1
            elif t > 0 and d["kind"] == "random_walk":
                level = _reflect(level + noise[t], lo, hi)
            K[t] = level
        if d["kind"] == "sinusoid":
            t = np.arange(T)
            K = np.clip(K + float(d["amplitude"]) * np.sin(2 * np.pi * t / float(d["period"]) + phase), lo, hi)
        return K

    def _jump_target(self, before: float, u: np.ndarray) -> float:
        jlo, jhi = self.jumps["range"]
        targets = jlo + u * (jhi - jlo)
        far = np.abs(targets - before) >= self.jumps["min_size"]
        # first draw far enough from the value before the jump (64 draws; the farthest one otherwise)
        return float(targets[np.argmax(far)] if far.any() else targets[np.argmax(np.abs(targets - before))])

    def init_angles(self, rng: np.random.Generator) -> np.ndarray:
        """Start angles (4,) in degrees of one cavity."""
        return np.array([rng.uniform(*self.init_angles_deg[a]) for a in ANGLE_NAMES])

    def sample(self, num_cavities: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """K (B, steps) and start angles (B, 4) in degrees, cavity i from its own generator."""
        Ks, angles = [], []
        for i in range(num_cavities):
            rng = self.cavity_rng(seed, i)
            Ks.append(self.K_trajectory(rng, self.start_K(i)))
            angles.append(self.init_angles(rng))
        return np.stack(Ks), np.stack(angles)


def _pair(value, name: str, allow_number: bool = False) -> tuple[float, float]:
    if allow_number and _finite(value):
        return float(value), float(value)
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 2 or not all(map(_finite, value)):
        raise ValueError(f"{name} must be a [low, high] pair of numbers, got {value!r}")
    lo, hi = float(value[0]), float(value[1])
    if lo > hi:
        raise ValueError(f"{name} must have low <= high, got {value!r}")
    return lo, hi


def _reflect(x: float, lo: float, hi: float) -> float:
    """Reflect x into [lo, hi] (a random walk with reflecting walls)."""
    if hi == lo:
        return lo
    span = 2 * (hi - lo)
    y = (x - lo) % span
    return lo + (y if y <= hi - lo else span - y)
