"""Derivative-free baselines that earlier self-tuning lasers used, on the live cavity.

Every evaluation of a setting is one agent step of the running cavity (the same step and
round-trip budget as every other controller), so exploring costs time out of lock, and a
setting that loses the pulse leaves the cavity in a continuous-wave state for the next
one (the cavity has hysteresis). Because K drifts, a remembered r goes stale: the
incumbent (best setting so far) is re-applied and re-measured before every
``candidates_per_remeasure`` candidates, and a candidate replaces it when its r is higher
than the incumbent's latest r.

* ``RandomSearch``: candidate = incumbent + N(0, sigma_deg^2) per angle, or, with
  probability ``global_prob``, uniform over ``range_deg``.
* ``HillClimb``: coordinate hill-climbing (compass search): probe incumbent +- step along one
  angle at a time; a success keeps direction and grows the step (x ``grow``, at most
  ``max_step_deg``), a failure on both sides shrinks it (x ``shrink``, at least
  ``min_step_deg``) and moves to the next angle.
* ``Genetic``: a genetic algorithm (Andral et al. 2015, Woodward & Kelleher 2016): a
  population of ``population`` settings per cavity, each evaluated for one step; then the
  ``elite`` best survive and the rest are children of tournament-selected parents (blend
  crossover, Gaussian mutation of ``sigma_deg``). The initial population is the start
  setting and uniform draws over ``range_deg``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from laserrl.control.checks import integer as _integer, positive as _positive, probability as _probability
from laserrl.control.esc import observed_r
from laserrl.envs.laser_env import ANGLE_NAMES


def _range(value: Sequence[float]) -> tuple[float, float]:
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
        raise ValueError(f"range_deg must be a [low, high] pair in degrees, got {value!r}")
    lo, hi = (float(x) for x in value)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"range_deg must be finite with low < high, got {value!r}")
    return lo, hi


class _IncumbentSearch:
    """Shared bookkeeping: alternate the incumbent and ``candidates_per_remeasure`` candidates."""

    def __init__(self, controlled, num_cavities: int, candidates_per_remeasure: int, seed: int):
        self.idx = [ANGLE_NAMES.index(a) for a in controlled]
        self.B, self.m = num_cavities, len(self.idx)
        self.per_remeasure = int(candidates_per_remeasure)
        self.rng = np.random.default_rng(seed)
        self.best = np.zeros((self.B, self.m))
        self.best_r = np.full(self.B, -np.inf)
        self.candidate = np.zeros((self.B, self.m))
        self.phase = 0  # 0: incumbent; 1..per_remeasure: candidates (the same for all cavities)

    def reset(self, obs, angles_deg: torch.Tensor) -> None:
        self.best = angles_deg[:, self.idx].cpu().numpy().astype(np.float64)
        self.best_r = np.full(self.B, -np.inf)
        self.phase = -1  # the first act applies the incumbent; its r is not a measurement of it yet

    def propose(self) -> np.ndarray:
        raise NotImplementedError

    def judge(self, accepted: np.ndarray) -> None:
        """Update the search state after a candidate (accepted per cavity)."""

    def act(self, obs, angles_deg: torch.Tensor) -> torch.Tensor:
        r = observed_r(obs)
        if self.phase == 0:
            self.best_r = r  # the incumbent's r under the current K
        elif self.phase > 0:
            accepted = r > self.best_r
            self.best = np.where(accepted[:, None], self.candidate, self.best)
            self.best_r = np.where(accepted, r, self.best_r)
            self.judge(accepted)
        self.phase = self.phase + 1 if 0 <= self.phase < self.per_remeasure else 0
        if self.phase > 0:
            self.candidate = self.propose()
        command = angles_deg.clone().to(torch.float64)
        command[:, self.idx] = torch.as_tensor(self.candidate if self.phase > 0 else self.best, dtype=torch.float64)
        return command


@dataclass
class RandomSearchParams:
    sigma_deg: float = 3.0
    global_prob: float = 0.1
    range_deg: Sequence[float] = (-90.0, 90.0)
    candidates_per_remeasure: int = 1

    def __post_init__(self):
        _positive(self, "sigma_deg")
        _probability(self, "global_prob")
        self.range_deg = _range(self.range_deg)
        _integer(self, "candidates_per_remeasure", 1)


class RandomSearch(_IncumbentSearch):
    name = "random_search"

    def __init__(self, params: RandomSearchParams, controlled, num_cavities: int, seed: int = 0):
        super().__init__(controlled, num_cavities, params.candidates_per_remeasure, seed)
        self.params = params

    def propose(self) -> np.ndarray:
        lo, hi = self.params.range_deg
        local = self.best + self.params.sigma_deg * self.rng.standard_normal((self.B, self.m))
        uniform = self.rng.uniform(lo, hi, (self.B, self.m))
        jump = self.rng.random(self.B) < self.params.global_prob
        return np.where(jump[:, None], uniform, local)


@dataclass
class HillClimbParams:
    step_deg: float = 2.0
    min_step_deg: float = 0.25
    max_step_deg: float = 4.0
    grow: float = 1.5
    shrink: float = 0.5
    candidates_per_remeasure: int = 1

    def __post_init__(self):
        _positive(self, "step_deg", "min_step_deg", "max_step_deg", "grow", "shrink")
        if not self.min_step_deg <= self.step_deg <= self.max_step_deg:
            raise ValueError(f"need min_step_deg <= step_deg <= max_step_deg, got {self.min_step_deg}, "
                             f"{self.step_deg}, {self.max_step_deg}")
        if self.grow < 1 or self.shrink >= 1:
            raise ValueError(f"need grow >= 1 and shrink < 1, got grow={self.grow}, shrink={self.shrink}")
        _integer(self, "candidates_per_remeasure", 1)


class HillClimb(_IncumbentSearch):
    name = "hill_climb"

    def __init__(self, params: HillClimbParams, controlled, num_cavities: int, seed: int = 0):
        super().__init__(controlled, num_cavities, params.candidates_per_remeasure, seed)
        self.params = params
        self.step = np.full((self.B, self.m), float(params.step_deg))
        self.coord = np.zeros(self.B, dtype=np.int64)
        self.sign = np.ones(self.B)

    def reset(self, obs, angles_deg) -> None:
        super().reset(obs, angles_deg)
        self.step[:] = self.params.step_deg
        self.coord[:] = 0
        self.sign[:] = 1.0

    def propose(self) -> np.ndarray:
        rows = np.arange(self.B)
        cand = self.best.copy()
        cand[rows, self.coord] += self.sign * self.step[rows, self.coord]
        return cand

    def judge(self, accepted: np.ndarray) -> None:
        p, rows = self.params, np.arange(self.B)
        s = self.step[rows, self.coord]
        self.step[rows, self.coord] = np.where(accepted, np.minimum(s * p.grow, p.max_step_deg), s)
        failed_both = ~accepted & (self.sign < 0)
        self.step[rows, self.coord] = np.where(failed_both, np.maximum(s * p.shrink, p.min_step_deg),
                                               self.step[rows, self.coord])
        # failure on the + side: try the - side; failure on both: next angle, + side first
        self.coord = np.where(failed_both, (self.coord + 1) % self.m, self.coord)
        self.sign = np.where(accepted, self.sign, np.where(self.sign > 0, -1.0, 1.0))


@dataclass
class GeneticParams:
    population: int = 8
    elite: int = 2
    tournament: int = 2
    sigma_deg: float = 3.0
    mutation_prob: float = 0.5
    range_deg: Sequence[float] = (-90.0, 90.0)

    def __post_init__(self):
        _integer(self, "population", 2)
        _integer(self, "elite", 1)
        _integer(self, "tournament", 1)
        if self.elite >= self.population:
            raise ValueError(f"elite ({self.elite}) must be smaller than population ({self.population})")
        if self.tournament > self.population:
            raise ValueError(f"tournament ({self.tournament}) must be <= population ({self.population})")
        _positive(self, "sigma_deg")
        _probability(self, "mutation_prob")
        self.range_deg = _range(self.range_deg)


class Genetic:
    """Generational GA with elitism, one individual evaluated per step (see the module docstring)."""

    name = "ga"

    def __init__(self, params: GeneticParams, controlled, num_cavities: int, seed: int = 0):
        self.params = params
        self.idx = [ANGLE_NAMES.index(a) for a in controlled]
        self.B, self.m, self.P = num_cavities, len(self.idx), int(params.population)
        self.rng = np.random.default_rng(seed)
        self.pop = np.zeros((self.B, self.P, self.m))
        self.fitness = np.full((self.B, self.P), -np.inf)
        self.i = -1  # index of the individual applied last; -1: none yet

    def reset(self, obs, angles_deg: torch.Tensor) -> None:
        lo, hi = self.params.range_deg
        self.pop = self.rng.uniform(lo, hi, (self.B, self.P, self.m))
        self.pop[:, 0] = angles_deg[:, self.idx].cpu().numpy()
        self.fitness[:] = -np.inf
        self.i = -1

    def _next_generation(self) -> None:
        p, rows = self.params, np.arange(self.B)[:, None]
        order = np.argsort(-self.fitness, axis=1)
        elite = self.pop[rows, order[:, : p.elite]]
        n_child = self.P - p.elite

        def tournament():
            entrants = self.rng.integers(0, self.P, (self.B, n_child, p.tournament))
            winner = np.take_along_axis(entrants, np.argmax(self.fitness[rows[:, :, None], entrants], -1)[..., None], -1)
            return self.pop[rows, winner[..., 0]]

        mother, father = tournament(), tournament()
        w = self.rng.random((self.B, n_child, self.m))
        child = mother + w * (father - mother)
        mutate = self.rng.random((self.B, n_child, self.m)) < p.mutation_prob
        child = child + mutate * p.sigma_deg * self.rng.standard_normal((self.B, n_child, self.m))
        self.pop = np.concatenate([elite, child], axis=1)
        self.fitness[:] = -np.inf

    def act(self, obs, angles_deg: torch.Tensor) -> torch.Tensor:
        if self.i >= 0:
            self.fitness[:, self.i] = observed_r(obs)
        self.i += 1
        if self.i == self.P:
            self._next_generation()
            self.i = 0
        command = angles_deg.clone().to(torch.float64)
        command[:, self.idx] = torch.as_tensor(self.pop[:, self.i], dtype=torch.float64)
        return command

    @property
    def best(self) -> np.ndarray:
        return self.pop[np.arange(self.B), np.argmax(self.fitness, axis=1)]
