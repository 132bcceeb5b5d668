"""One agent step of the batched cavity, as a pure function of explicit state.

An agent step puts the plates at new angles alpha = (alpha1, alpha2, alpha3, alpha_p) and
runs the cavity round trip by round trip (the coupled NLS of the fiber, then
J1 JP J2 J3) until the field has answered them:

    at least ``min_round_trips`` round trips, then stop at the first j with
    norm(phi_j - phi_{j-1}) / norm(phi_{j-1}) < tol,  phi = sqrt(|u|^2 + |v|^2),
    or after ``max_round_trips`` round trips in all;

the step's reward is r = E / M4 of the state it ends in. Why at least two round trips:
J1 (alpha1) is the last element of the round trip and unitary, so the first round trip
after a change of alpha1 alone gives the same phi as the angle before it; a settled
cavity would pass the stopping test after that one round trip and the step would show
the old angle. From the second round trip on every plate has acted on the intensity.
``min_round_trips = 1`` is the paper's rule exactly (``experiment=paper_exact``).

``step_cavity`` is that step for any new angles (the analysis sweeps and paths, the
control plant), ``step`` the same for a discrete action of a task (the env). Everything
they need is passed in: the state (``CavityState``), the numerics (``StepNumerics``) and
the physics (``CavityParams``); nothing is kept between calls.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Sequence

import torch
from tensordict import tensorclass

from laserrl.envs.actions import action_to_deltas
from laserrl.physics import CavityParams, NonFiniteFieldError, reward_terms, run_to_convergence
from laserrl.physics.checks import CAVITY_KEYS
from laserrl.physics.instruments import Instruments, measure, measured_reward

__all__ = ["CavityState", "StepNumerics", "StepOutput", "apply_action", "drift_K", "observe", "observe_measured",
           "step", "step_cavity", "wrap_angle"]


def wrap_angle(a: torch.Tensor) -> torch.Tensor:
    """Wrap radians to [-pi/2, pi/2): every Jones matrix has period pi."""
    return torch.remainder(a + math.pi / 2, math.pi) - math.pi / 2


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) \
            or int(value) != value or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


@dataclass(frozen=True)
class StepNumerics:
    """How one agent step runs the cavity (see the module docstring).

    Attributes:
        max_round_trips: round trips per step at most (the paper: 500).
        tol: convergence tolerance of phi between round trips (the paper: 1e-6).
        min_round_trips: round trips per step at least; 1 is the paper's rule.
        compile: ``torch.compile`` the round trip.
    """

    max_round_trips: int = 30
    tol: float = 1e-5
    min_round_trips: int = 2
    compile: bool = False

    def __post_init__(self):
        for name in ("max_round_trips", "min_round_trips"):
            object.__setattr__(self, name, _positive_int(getattr(self, name), name))
        if isinstance(self.tol, bool) or not isinstance(self.tol, numbers.Real) or not self.tol >= 0:
            raise ValueError(f"tol must be a number >= 0, got {self.tol!r}")
        if self.min_round_trips > self.max_round_trips:
            raise ValueError(f"min_round_trips ({self.min_round_trips}) must be <= max_round_trips "
                             f"({self.max_round_trips})")


@tensorclass
class CavityState:
    """The batched state of B cavities: complex fields ``u``, ``v`` (B, n), the four plate
    angles (B, 4) in radians (alpha1, alpha2, alpha3, alpha_p), the birefringence ``K`` (B,)
    and the agent steps taken in the episode, ``step_count`` (B,); ``cavity`` (B, 5): each
    cavity's own D, E0, tau, g0, Gamma (``laserrl.physics.checks.CAVITY_KEYS``), or None when
    every cavity is the nominal one of ``CavityParams``."""

    u: torch.Tensor
    v: torch.Tensor
    angles: torch.Tensor
    K: torch.Tensor
    step_count: torch.Tensor
    cavity: torch.Tensor | None = None


@tensorclass
class StepOutput:
    """What one step measured, per cavity: ``r`` = E / M4 of the new state, the
    ``round_trips`` it ran and whether it ``converged`` within ``max_round_trips``."""

    r: torch.Tensor
    round_trips: torch.Tensor
    converged: torch.Tensor


def step_cavity(state: CavityState, angles: torch.Tensor, params: CavityParams,
                numerics: StepNumerics) -> tuple[CavityState, StepOutput]:
    """The cavities after one agent step at ``angles`` (B, 4) radians (wrapped here).

    Raises ``NonFiniteFieldError`` naming the cavity, its angles and K if a field becomes
    NaN or infinite."""
    angles = wrap_angle(angles.to(torch.float64))
    try:
        result = run_to_convergence(state.u, state.v, angles, state.K, params, tol=numerics.tol,
                                    max_round_trips=numerics.max_round_trips,
                                    min_round_trips=numerics.min_round_trips, compile=numerics.compile,
                                    cavity=state.cavity)
    except NonFiniteFieldError as err:
        i = err.cavities[0]
        raise NonFiniteFieldError(
            err.cavities,
            f" at angles {torch.rad2deg(angles[i]).tolist()} deg and K = {float(state.K[i])} (cavity {i} of the batch)",
        ) from None
    r = reward_terms(result.u, result.v, params)[2]
    new = CavityState(u=result.u, v=result.v, angles=angles, K=state.K, step_count=state.step_count + 1,
                      cavity=state.cavity, batch_size=state.batch_size)
    return new, StepOutput(r=r, round_trips=result.round_trips, converged=result.converged,
                           batch_size=state.batch_size)


def draw_cavities(params: CavityParams, spread: Sequence[float], batch: int, generator: torch.Generator | None = None,
                  device=None) -> torch.Tensor:
    """(batch, 5) per-cavity D, E0, tau, g0, Gamma, each drawn uniformly within +-``spread`` (one
    fraction per parameter, ``CAVITY_KEYS`` order) of ``params``' value: cavities other than the
    nominal one, for training a controller that does not rely on the model being exact."""
    nominal = torch.tensor([float(getattr(params, k)) for k in CAVITY_KEYS], dtype=torch.float64)
    frac = torch.tensor([float(f) for f in spread], dtype=torch.float64)
    where = generator.device if generator is not None else "cpu"
    uni = torch.rand((batch, len(CAVITY_KEYS)), generator=generator, dtype=torch.float64, device=where).cpu()
    return (nominal * (1.0 + frac * (2.0 * uni - 1.0))).to(device)


def drift_K(K: torch.Tensor, low: float, high: float, sigma: float, jump_prob: float,
            generator: torch.Generator | None = None) -> torch.Tensor:
    """K (B,) one agent step later: a random walk K + sigma xi reflected into [low, high], and
    with probability ``jump_prob`` per cavity a jump to a fresh uniform draw in [low, high]
    (the birefringence of a real fiber drifts with temperature and jumps when it is touched)."""
    B, where = K.shape[0], (generator.device if generator is not None else K.device)
    xi = torch.randn(B, generator=generator, dtype=torch.float64, device=where).to(K.device)
    uni = torch.rand((2, B), generator=generator, dtype=torch.float64, device=where).to(K.device)
    width = high - low
    walked = K + sigma * xi
    if width > 0:  # reflect at the bounds (period 2 width); values inside stay exactly as they are
        x = torch.remainder(walked - low, 2 * width)
        walked = torch.where((walked < low) | (walked > high), low + torch.where(x > width, 2 * width - x, x), walked)
    return torch.where(uni[0] < jump_prob, low + uni[1] * width, walked)


def apply_action(angles: torch.Tensor, action: torch.Tensor, steps_rad: torch.Tensor,
                 controlled_index: torch.Tensor) -> torch.Tensor:
    """The angles (B, 4) after discrete ``action`` (B,) (``laserrl.envs.actions``) turns the
    ``controlled_index`` plates by their ``steps_rad`` (m,) or per cavity (B, m), wrapped to [-pi/2, pi/2)."""
    out = angles.clone()
    out[:, controlled_index] = wrap_angle(angles[:, controlled_index] + action_to_deltas(action, steps_rad))
    return out


def turn_steps(steps: torch.Tensor, fine_steps: torch.Tensor, signal: torch.Tensor, fine_from: float) -> torch.Tensor:
    """(B, m) plate turn of each cavity: ``fine_steps`` (m,) where its reward signal (B,) is at least
    ``fine_from`` (near a lock), else ``steps`` (m,) (a coarse search)."""
    return torch.where((signal >= fine_from).unsqueeze(-1), fine_steps, steps)


def step(state: CavityState, action: torch.Tensor, steps_rad: torch.Tensor, controlled_index: torch.Tensor,
         params: CavityParams, numerics: StepNumerics) -> tuple[CavityState, StepOutput]:
    """One agent step of a discrete action: ``apply_action``, then ``step_cavity``."""
    return step_cavity(state, apply_action(state.angles, action, steps_rad, controlled_index), params, numerics)


def observe_measured(state: CavityState, params: CavityParams, instruments: Instruments, matrix: torch.Tensor,
                     generator: torch.Generator | None = None) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """What the agent sees with ``observation="measured"``: the instruments' readings
    (``laserrl.physics.instruments``) ``spectrum`` (B, bins), ``energy`` (B, 1), ``autocorrelation``
    (B, points) if there is an autocorrelator, and ``angles`` (B, 4), all float32; with the reward
    of those readings, ``r_measured`` (B,). ``matrix``: the OSA's ``spectrum_matrix``."""
    m = measure(state.u, state.v, params, instruments, matrix, generator)
    obs = {"spectrum": m.spectrum.to(torch.float32), "energy": m.energy.unsqueeze(-1).to(torch.float32)}
    if m.autocorrelation is not None:
        obs["autocorrelation"] = m.autocorrelation.to(torch.float32)
    obs["angles"] = state.angles.to(torch.float32)
    return obs, measured_reward(m, instruments.reward)


def observe(state: CavityState) -> dict[str, torch.Tensor]:
    """What the agent sees: ``fields`` (B, 4, n) float32 = (Re u, Im u, Re v, Im v) and
    ``angles`` (B, 4) float32 radians. K is not observed."""
    u, v = state.u, state.v
    return {"fields": torch.stack([u.real, u.imag, v.real, v.imag], dim=1).to(torch.float32),
            "angles": state.angles.to(torch.float32)}
