"""Batched TorchRL environment of the NPR mode-locked fiber laser.

The env only adapts the pure agent step ``laserrl.envs.step.step``: it keeps the batched
``CavityState`` (fields, angles, birefringence K, step count), declares the specs, samples
initial states at reset (all cavities, or those in the ``_reset`` mask) and reports
r = E / M4 of the state each step ends in.

Observation (``task.observation``): ``fields`` (B, 4, n) float32 = (Re u, Im u, Re v, Im v),
or with ``"measured"`` what instruments read (``spectrum``, ``energy``, ``autocorrelation``:
``laserrl.physics.instruments``), and ``angles`` (B, 4) in radians (alpha1, alpha2, alpha3,
alpha_p), wrapped to [-pi/2, pi/2). K is the latent disturbance and is not observed.
Diagnostics that a policy should not read are put next to the observation: ``r`` (the
paper's r of the state, which evaluation reads), ``round_trips``. The reward is r, or with
measured observations the readings' own ``r_measured``, minus ``move_cost`` when a plate turns
(with ``move_cost_from``: only when it turns from a state whose reward signal is at least that).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, fields as dc_fields
from typing import Mapping, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from laserrl.envs.actions import hold_action, num_actions
from laserrl.envs.step import (CavityState, StepNumerics, apply_action, draw_cavities, drift_K, observe,
                               observe_measured, step, turn_steps, wrap_angle)
from laserrl.physics.checks import CAVITY_KEYS
from laserrl.physics.instruments import Instruments, spectrum_matrix
from laserrl.physics.run import CONVERGENCE_FLOOR
from laserrl.physics import CavityParams, noise_fields, reward_terms, sech_fields

ANGLE_NAMES = ("alpha1", "alpha2", "alpha3", "alpha_p")
OBSERVATIONS = ("fields", "measured")
_DTYPES = {"complex64": torch.complex64, "complex128": torch.complex128}
#: Largest initial field amplitude (sech_amplitude, noise_scale): the cavity's states peak at
#: |u|^2 + |v|^2 of order 1-10, and far larger fields can be compressed within a round trip
#: beyond what the physics accepts (MAX_PEAK_POWER), which would stop an episode midway.
MAX_INIT_AMPLITUDE = 10.0


def finite_number(value, name: str) -> float:
    """A finite real number (not a bool, string or list), as float; otherwise a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def _range(value, name: str) -> tuple[float, float]:
    """A fixed value or a [lo, hi] range, as (lo, hi)."""
    if isinstance(value, Sequence) and not isinstance(value, str) and len(value) == 2:
        lo, hi = (finite_number(x, name) for x in value)
    elif isinstance(value, numbers.Real) and not isinstance(value, bool):
        lo = hi = finite_number(value, name)
    else:
        raise ValueError(f"{name} must be a number or a [low, high] pair, got {value!r}")
    if lo > hi:
        raise ValueError(f"{name} must have low <= high, got {value!r}")
    return lo, hi


def _sequence(value, name: str) -> tuple:
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise ValueError(f"{name} must be a list, got {value!r}")
    return tuple(value)


def _plate_steps(value, name: str, count: int) -> tuple[float, ...]:
    """``steps_deg`` / ``fine_steps_deg``: one finite step > 0 per controlled angle."""
    steps = tuple(finite_number(s, name) for s in _sequence(value, name))
    if len(steps) != count:
        raise ValueError(f"{name} needs one step per controlled angle ({count}), got {steps!r}")
    if not all(s > 0 for s in steps):
        raise ValueError(f"{name} must be positive and finite, got {steps!r}")
    return steps


def _spread(value) -> tuple[float, ...] | None:
    """``physics_spread`` as one fraction in [0, 0.5] per parameter of ``CAVITY_KEYS``, or None."""
    if value is None:
        return None
    if isinstance(value, Mapping):
        unknown = set(value) - set(CAVITY_KEYS)
        if unknown:
            raise ValueError(f"physics_spread: unknown parameter(s) {sorted(unknown)}; choose from {list(CAVITY_KEYS)}")
        fractions = [value.get(k, 0.0) for k in CAVITY_KEYS]
    else:
        fractions = [value] * len(CAVITY_KEYS)
    for k, f in zip(CAVITY_KEYS, fractions):
        if not 0 <= finite_number(f, f"physics_spread.{k}") <= 0.5:
            raise ValueError(f"physics_spread.{k} must be a fraction in [0, 0.5], got {f!r}")
    return tuple(float(f) for f in fractions) if any(fractions) else None


def policy_keys(task: "LaserTask") -> tuple[str, ...]:
    """The observation keys a policy reads for ``task``'s observation (not the diagnostics r,
    r_measured, round_trips, step_count)."""
    if task.observation == "fields":
        return ("fields", "angles")
    return ("spectrum", "energy", *(("autocorrelation",) if task.instruments.autocorrelation_points else ()), "angles")


@dataclass
class LaserTask:
    """What the agent controls and how episodes start. Angles in degrees.

    Defaults are the paper's single-input task: K = 0.1, alpha2 = 3, alpha3 = 28,
    alpha_p = 88 deg; alpha1 controlled in 2 deg steps from uniform [-40, -10] deg;
    u = v = 0.5 sech(t/2).
    """

    controlled: Sequence[str] = ("alpha1",)
    steps_deg: Sequence[float] = (2.0,)
    # initial angle of each of the four plates: a number or a [low, high] range
    init_angles_deg: dict = field(default_factory=lambda: {"alpha1": (-40.0, -10.0), "alpha2": 3.0, "alpha3": 28.0, "alpha_p": 88.0})
    K: float | Sequence[float] = 0.1  # fixed, or a [low, high] range sampled at reset
    # within an episode K may move inside that range: a random walk of K_drift per step (reflected at its
    # ends) and, with probability K_jump per step, a jump to a fresh draw (laserrl.envs.step.drift_K)
    K_drift: float = 0.0
    K_jump: float = 0.0
    init_fields: str = "sech"  # "sech" or "noise"
    sech_amplitude: float = 0.5
    sech_width: float = 2.0
    noise_scale: float = 0.1
    max_round_trips: int = 500  # per agent step (paper: 500)
    # per agent step at least: 2 lets a turn of alpha1 act within its own step (laserrl.envs.step); paper: 1
    min_round_trips: int = 2
    # convergence tolerance per agent step; None = the finest the dtype resolves:
    # the paper's 1e-6 with complex128, 1e-5 with complex64 (see CONVERGENCE_FLOOR)
    tol: float | None = None
    max_steps: int = 40  # episode length (paper: 40 in training, 20 at inference)
    # subtracted from the reward r of a step that turns a plate (0: the paper's reward); r itself,
    # which evaluation reads, is unchanged
    move_cost: float = 0.0
    # charge move_cost only for moves made from a state whose reward signal (r, or r_measured with measured
    # observations) is at least this: a cost for leaving a lock, not for searching; None: every move
    move_cost_from: float | None = None
    # finer turns near a lock: a turn from a state whose reward signal (as for move_cost_from) is at least
    # fine_from moves the plates by fine_steps_deg (one per controlled angle) instead of steps_deg, so that
    # steps_deg can be coarse for the search; None: steps_deg everywhere
    fine_steps_deg: Sequence[float] | None = None
    fine_from: float | None = None
    dtype: str = "complex64"
    compile: bool = False
    # what the agent observes: "fields" (u, v with their phase: the paper) or "measured" (the readings of
    # ``instruments``, laserrl.physics.instruments; the training reward is then theirs too)
    observation: str = "fields"
    instruments: Instruments | Mapping | None = None  # settings of the instruments (None: their defaults)
    # cavities other than the nominal one: at every reset each cavity draws D, E0, tau, g0, Gamma uniformly
    # within +- this fraction of the physics' value (one number for all, or {name: fraction}); None: all nominal
    physics_spread: float | Mapping | None = None

    def __post_init__(self):
        self.controlled = _sequence(self.controlled, "controlled")
        if not all(isinstance(name, str) for name in self.controlled):
            raise ValueError(f"controlled must name angles of {ANGLE_NAMES}, got {self.controlled!r}")
        if not self.controlled or len(set(self.controlled)) != len(self.controlled):
            raise ValueError(f"controlled must name 1 to 4 distinct angles of {ANGLE_NAMES}, got {self.controlled!r}")
        for name in self.controlled:
            if name not in ANGLE_NAMES:
                raise ValueError(f"controlled: unknown angle {name!r}; choose from {ANGLE_NAMES}")
        self.steps_deg = _plate_steps(self.steps_deg, "steps_deg", len(self.controlled))
        if not isinstance(self.init_angles_deg, Mapping):
            raise ValueError(f"init_angles_deg must map angle names to a number or a [low, high] pair, got {self.init_angles_deg!r}")
        init = dict(self.init_angles_deg)
        unknown = set(init) - set(ANGLE_NAMES)
        if unknown:
            raise ValueError(f"init_angles_deg: unknown angle(s) {sorted(unknown)}; choose from {ANGLE_NAMES}")
        missing = set(ANGLE_NAMES) - set(init)
        if missing:
            raise ValueError(f"init_angles_deg must give all four angles, missing {sorted(missing)}")
        self.init_angles_deg = {k: _range(init[k], f"init_angles_deg.{k}") for k in ANGLE_NAMES}
        self.K = _range(self.K, "K")
        if not finite_number(self.K_drift, "K_drift") >= 0:
            raise ValueError(f"K_drift must be >= 0, got {self.K_drift!r}")
        if not 0 <= finite_number(self.K_jump, "K_jump") <= 1:
            raise ValueError(f"K_jump must be a probability in [0, 1], got {self.K_jump!r}")
        if (self.K_drift or self.K_jump) and self.K[0] == self.K[1]:
            raise ValueError(f"K_drift and K_jump move K within a range: give K as [low, high], got {self.K[0]!r}")
        if self.init_fields not in ("sech", "noise"):
            raise ValueError(f"init_fields must be 'sech' or 'noise', got {self.init_fields!r}")
        for name, largest in (("sech_amplitude", MAX_INIT_AMPLITUDE), ("sech_width", math.inf),
                              ("noise_scale", MAX_INIT_AMPLITUDE)):
            value = finite_number(getattr(self, name), name)
            if not 0 < value <= largest:
                raise ValueError(f"{name} must be > 0{f' and <= {largest:g}' if largest < math.inf else ''}, got {value!r}")
        for name in ("max_round_trips", "min_round_trips", "max_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) \
                    or int(value) != value or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if not finite_number(self.move_cost, "move_cost") >= 0:
            raise ValueError(f"move_cost must be >= 0, got {self.move_cost!r}")
        if self.move_cost_from is not None:
            self.move_cost_from = finite_number(self.move_cost_from, "move_cost_from")
        if (self.fine_steps_deg is None) != (self.fine_from is None):
            raise ValueError(f"fine_steps_deg and fine_from go together (finer steps from a reward signal on), got "
                             f"fine_steps_deg={self.fine_steps_deg!r}, fine_from={self.fine_from!r}")
        if self.fine_steps_deg is not None:
            self.fine_steps_deg = _plate_steps(self.fine_steps_deg, "fine_steps_deg", len(self.controlled))
            self.fine_from = finite_number(self.fine_from, "fine_from")
        if not isinstance(self.dtype, str) or self.dtype not in _DTYPES:
            raise ValueError(f"dtype must be one of {sorted(_DTYPES)}, got {self.dtype!r}")
        if self.observation not in OBSERVATIONS:
            raise ValueError(f"observation must be one of {OBSERVATIONS}, got {self.observation!r}")
        if isinstance(self.instruments, Mapping):
            try:
                self.instruments = Instruments(**dict(self.instruments))
            except TypeError as err:  # an unknown setting
                known = [f.name for f in dc_fields(Instruments)]
                raise ValueError(f"instruments: {err}; settings: {known}") from None
            except ValueError as err:
                raise ValueError(f"instruments.{err}") from None
        elif self.instruments is None:
            self.instruments = Instruments()
        elif not isinstance(self.instruments, Instruments):
            raise ValueError(f"instruments must map instrument settings to values, got {self.instruments!r}")
        self.physics_spread = _spread(self.physics_spread)
        if self.tol is None:
            self.tol = max(1e-6, CONVERGENCE_FLOOR[_DTYPES[self.dtype]])
        if finite_number(self.tol, "tol") < 0:
            raise ValueError(f"tol must be >= 0, got {self.tol!r}")
        self.numerics  # StepNumerics checks the rules between the round-trip bounds

    @property
    def numerics(self) -> StepNumerics:
        """The numerics of one agent step of this task."""
        return StepNumerics(max_round_trips=self.max_round_trips, tol=self.tol, min_round_trips=self.min_round_trips,
                            compile=self.compile)

    @property
    def controlled_index(self) -> list[int]:
        return [ANGLE_NAMES.index(n) for n in self.controlled]

    @property
    def num_actions(self) -> int:
        return num_actions(len(self.controlled))


class LaserCavityEnv(EnvBase):
    """B cavities stepped together; see the module docstring.

    Args:
        batch_size: number of cavities, an int or [N].
        task: a ``LaserTask``; any of its fields may be given as keyword arguments instead.
        params: ``CavityParams`` of the physics (paper defaults).
        device: torch device. seed: seed of the env's own ``torch.Generator``.
    """

    batch_locked = True

    def __init__(self, batch_size=1, task: LaserTask | None = None, params: CavityParams | None = None,
                 device=None, seed: int | None = None, **task_kwargs):
        if isinstance(batch_size, int):
            batch_size = [batch_size]
        batch_size = torch.Size(batch_size)
        if len(batch_size) != 1 or batch_size[0] < 1:
            raise ValueError(f"batch_size must be a positive int or [N], got {list(batch_size)}")
        if task is not None and task_kwargs:
            raise ValueError("give either task= or task keyword arguments, not both")
        known = {f.name for f in dc_fields(LaserTask)}
        unknown = set(task_kwargs) - known
        if unknown:
            raise ValueError(f"unknown LaserCavityEnv argument(s) {sorted(unknown)}; task fields are {sorted(known)}")
        self.task = task if task is not None else LaserTask(**task_kwargs)
        self.params = params if params is not None else CavityParams()
        super().__init__(device=device or "cpu", batch_size=batch_size)
        self._cdtype = _DTYPES[self.task.dtype]
        self._rdtype = torch.float64 if self._cdtype == torch.complex128 else torch.float32
        n, B = self.params.n, batch_size[0]
        dev = self.device
        t = self.task
        self._ctrl_idx = torch.tensor(t.controlled_index, device=dev)
        self._hold = hold_action(len(t.controlled))
        self._steps = torch.tensor([math.radians(s) for s in t.steps_deg], dtype=torch.float64, device=dev)
        self._fine_steps = None if t.fine_steps_deg is None else \
            torch.tensor([math.radians(s) for s in t.fine_steps_deg], dtype=torch.float64, device=dev)
        lo_hi = torch.tensor([t.init_angles_deg[k] for k in ANGLE_NAMES], dtype=torch.float64, device=dev)
        self._angle_lo, self._angle_hi = torch.deg2rad(lo_hi[:, 0]), torch.deg2rad(lo_hi[:, 1])
        self._rng = torch.Generator(device=dev)
        self._rng.manual_seed(seed if seed is not None else int(torch.empty((), dtype=torch.int64).random_()))
        self._numerics = self.task.numerics
        self._measured = self.task.observation == "measured"
        if self._measured:
            try:
                self.task.instruments.check_grid(self.params)
            except ValueError as err:
                raise ValueError(f"instruments.{err}") from None
            self._osa = spectrum_matrix(self.params, self.task.instruments, dtype=self._rdtype, device=dev)
        self._pending: CavityState | None = None  # a saved state the next full reset continues (continue_from)
        self._start: TensorDictBase | None = None  # init_angles / init_K for the next reset (reset_at)
        self._reported: torch.Tensor | None = None  # (B, 4) angles the observation shows instead of the true ones
        self._signal: torch.Tensor | None = None  # (B,) reward signal of the current state (move_cost_from)
        self.state = CavityState(
            u=torch.zeros(B, n, dtype=self._cdtype, device=dev), v=torch.zeros(B, n, dtype=self._cdtype, device=dev),
            angles=torch.zeros(B, 4, dtype=torch.float64, device=dev), K=torch.zeros(B, dtype=torch.float64, device=dev),
            step_count=torch.zeros(B, dtype=torch.int64, device=dev), batch_size=[B], device=dev,
            cavity=None if self.task.physics_spread is None else draw_cavities(self.params, (0.0,) * 5, B, device=dev))
        self._make_specs()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        B, n, dev = self.batch_size, self.params.n, self.device
        if self._measured:
            ins = self.task.instruments
            seen = {"spectrum": Unbounded(shape=(*B, ins.spectrum_bins), dtype=torch.float32, device=dev),
                    "energy": Unbounded(shape=(*B, 1), dtype=torch.float32, device=dev)}
            if ins.autocorrelation_points:
                seen["autocorrelation"] = Unbounded(shape=(*B, ins.autocorrelation_points), dtype=torch.float32, device=dev)
            seen["r_measured"] = Unbounded(shape=(*B, 1), dtype=torch.float32, device=dev)  # the readings' reward
        else:
            seen = {"fields": Unbounded(shape=(*B, 4, n), dtype=torch.float32, device=dev)}
        self.observation_spec = Composite(
            **seen,
            angles=Bounded(low=-math.pi / 2, high=math.pi / 2, shape=(*B, 4), dtype=torch.float32, device=dev),
            r=Unbounded(shape=(*B, 1), dtype=torch.float32, device=dev),
            round_trips=Unbounded(shape=(*B, 1), dtype=torch.int64, device=dev),
            step_count=Unbounded(shape=(*B, 1), dtype=torch.int64, device=dev),
            shape=B,
            device=dev,
        )
        self.action_spec = Categorical(self.task.num_actions, shape=B, device=dev)
        self.reward_spec = Unbounded(shape=(*B, 1), dtype=torch.float32, device=dev)
        flag = Categorical(2, shape=(*B, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=B, device=dev)

    # ------------------------------------------------------------------ helpers
    def _observation(self, r: torch.Tensor, round_trips: torch.Tensor) -> TensorDict:
        """The observation of the current state; measured readings draw their noise from the env's generator."""
        if self._measured:
            seen, r_measured = observe_measured(self.state, self.params, self.task.instruments, self._osa, self._rng)
            seen["r_measured"] = r_measured.to(torch.float32).unsqueeze(-1)
        else:
            seen = observe(self.state)
        if self._reported is not None:  # a controller's read-back of its commands (set_angles(..., reported=))
            seen["angles"] = self._reported.to(torch.float32)
        return TensorDict(
            **seen,
            r=r.to(torch.float32).unsqueeze(-1),
            round_trips=round_trips.unsqueeze(-1),
            step_count=self.state.step_count.unsqueeze(-1).clone(),
            batch_size=self.batch_size,
            device=self.device,
        )

    def _sample_initial(self):
        """A fresh initial state for every cavity (the caller keeps only the reset ones)."""
        B, dev, t = self.batch_size[0], self.device, self.task
        uni = torch.rand((B, 5), generator=self._rng, dtype=torch.float64, device=dev)
        angles = self._angle_lo + uni[:, :4] * (self._angle_hi - self._angle_lo)
        K = t.K[0] + uni[:, 4] * (t.K[1] - t.K[0])
        if t.init_fields == "sech":
            u, v = sech_fields(B, self.params, t.sech_amplitude, t.sech_width, dtype=self._cdtype, device=dev)
        else:
            u, v = noise_fields(B, self.params, self._rng, t.noise_scale, dtype=self._cdtype, device=dev)
        return u, v, wrap_angle(angles), K

    # ------------------------------------------------------------------ EnvBase API
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        """Reset all cavities, or those in the ``_reset`` mask. Optional entries of the
        input: ``init_angles`` (B, 4) radians and ``init_K`` (B,) replace the sampled ones."""
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(self.batch_size)
        if mask is None and self._pending is not None:  # the episodes in flight of a checkpointed run
            self.state, self._pending = self._pending, None
            return self._reset_output()
        u, v, angles, K = self._sample_initial()
        self._reported = None
        # explicit initial state for evaluation protocols: (B, 4) radians / (B,) K, in the input or from reset_at
        start = tensordict if tensordict is not None and ("init_angles" in tensordict.keys() or "init_K" in tensordict.keys()) \
            else self._start
        if start is not None and "init_angles" in start.keys():
            angles = wrap_angle(start.get("init_angles").to(device=self.device, dtype=torch.float64).reshape(angles.shape))
        if start is not None and "init_K" in start.keys():
            K = start.get("init_K").to(device=self.device, dtype=torch.float64).reshape(K.shape)
        cavity = None if self.task.physics_spread is None else \
            draw_cavities(self.params, self.task.physics_spread, self.batch_size[0], self._rng, device=self.device)
        fresh = CavityState(u=u, v=v, angles=angles, K=K, step_count=torch.zeros_like(self.state.step_count),
                            cavity=cavity, batch_size=self.batch_size, device=self.device)
        # sync-free partial reset: sample for all, keep where the mask is set
        self.state = fresh if mask is None else fresh.where(mask, self.state)
        previous = self._signal
        out = self._reset_output()
        if mask is not None and previous is not None:  # the others keep the signal their last step read
            self._signal = torch.where(mask, self._signal, previous)
        return out

    def _reset_output(self) -> TensorDictBase:
        r = reward_terms(self.state.u, self.state.v, self.params)[2]
        out = self._observation(r, torch.zeros_like(self.state.step_count))
        out.set("done", torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device))
        out.set("terminated", torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device))
        out.set("truncated", torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device))
        self._signal = self._signal_of(out)
        return out

    def _signal_of(self, out: TensorDictBase) -> torch.Tensor:
        """(B,) the reward signal of an observation: r, or with measured observations r_measured."""
        return out.get("r_measured" if self._measured else "r").reshape(self.batch_size)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").reshape(self.batch_size)
        t = self.task
        if t.K_drift or t.K_jump:  # K for this step
            self.state.K = drift_K(self.state.K, t.K[0], t.K[1], t.K_drift, t.K_jump, self._rng)
        steps = self._steps
        if self._fine_steps is not None and self._signal is not None:  # (B, m): fine steps near a lock
            steps = turn_steps(self._steps, self._fine_steps, self._signal, t.fine_from)
        if self._reported is not None:  # the read-back moves with the action as the plates do
            self._reported = apply_action(self._reported, action, steps, self._ctrl_idx)
        self.state, measured = step(self.state, action, steps, self._ctrl_idx, self.params, self._numerics)
        out = self._observation(measured.r, measured.round_trips)
        # the training reward: r, or with measured observations the readings' r_measured
        reward = out.get("r_measured").squeeze(-1) if self._measured else measured.r
        if self.task.move_cost:
            charged = action != self._hold
            if self.task.move_cost_from is not None and self._signal is not None:
                charged = charged & (self._signal >= self.task.move_cost_from)
            reward = reward - self.task.move_cost * charged.to(reward.dtype)
        self._signal = self._signal_of(out)
        out.set("reward", reward.to(torch.float32).unsqueeze(-1))
        truncated = (self.state.step_count >= self.task.max_steps).unsqueeze(-1)
        out.set("truncated", truncated)
        out.set("terminated", torch.zeros_like(truncated))
        out.set("done", truncated.clone())
        return out

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_())
        self._rng.manual_seed(int(seed))

    # ------------------------------------------------------------------ checkpoints
    def snapshot(self) -> dict:
        """The cavities' state and the env's generator, as plain tensors (for a run's checkpoint)."""
        st = self.state
        return {"state": {"u": st.u.clone(), "v": st.v.clone(), "angles": st.angles.clone(), "K": st.K.clone(),
                          "step_count": st.step_count.clone(), **({} if st.cavity is None else {"cavity": st.cavity.clone()})},
                "rng": self._rng.get_state()}

    def continue_from(self, snapshot: Mapping) -> None:
        """Continue a ``snapshot()``: the next full reset returns its state (so a collector built on
        this env carries on the episodes in flight) and the generator goes on from its state."""
        try:
            saved = snapshot["state"]
            like = {"u": (self.state.u, (*self.batch_size, self.params.n)), "v": (self.state.v, (*self.batch_size, self.params.n)),
                    "angles": (self.state.angles, (*self.batch_size, 4)), "K": (self.state.K, tuple(self.batch_size)),
                    "step_count": (self.state.step_count, tuple(self.batch_size))}
            if self.state.cavity is not None:
                like["cavity"] = (self.state.cavity, (*self.batch_size, 5))
            values = {}
            for key, (ref, shape) in like.items():
                value = saved[key]
                if not isinstance(value, torch.Tensor) or tuple(value.shape) != shape or value.dtype != ref.dtype:
                    raise ValueError(f"{key}: expected {ref.dtype} of shape {shape}")
                values[key] = value.to(self.device)
            rng = snapshot["rng"]
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"the saved env state does not fit this env ({err})") from None
        self._pending = CavityState(**values, batch_size=self.batch_size, device=self.device)
        self._rng.set_state(rng)

    # ------------------------------------------------------------------ introspection
    @property
    def K(self) -> torch.Tensor:
        """Current birefringence of every cavity (hidden from the agent)."""
        return self.state.K.clone()

    def set_K(self, K) -> None:
        """Set the birefringence of every cavity, e.g. to model drift between steps."""
        K = torch.as_tensor(K, dtype=torch.float64, device=self.device)
        K = K.expand(self.batch_size) if K.ndim == 0 else K
        if K.shape != self.batch_size or not bool(torch.isfinite(K).all()):
            raise ValueError(f"K must be finite with shape {tuple(self.batch_size)}, got {tuple(K.shape)}")
        self.state.K = K.clone()

    def set_angles(self, angles, reported=None) -> None:
        """Set all four angles of every cavity, (B, 4) radians (wrapped to [-pi/2, pi/2)):
        continuous commands of other controllers (``laserrl.control``) between steps. With
        ``reported`` (B, 4) radians, the observations show those angles (what a controller
        commanded and reads back) instead of where the plates are, until the next reset."""
        checked = []
        for name, value in (("angles", angles), ("reported", reported)):
            if value is None:
                checked.append(None)
                continue
            value = torch.as_tensor(value, dtype=torch.float64, device=self.device)
            if value.shape != (*self.batch_size, 4) or not bool(torch.isfinite(value).all()):
                raise ValueError(f"{name} must be finite with shape {(*self.batch_size, 4)}, got {tuple(value.shape)}")
            checked.append(wrap_angle(value.clone()))
        self.state.angles = checked[0]
        self._reported = checked[1]

    def fields(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Current complex fields (u, v), (B, n)."""
        return self.state.u.clone(), self.state.v.clone()

    def angles_deg(self) -> torch.Tensor:
        return torch.rad2deg(self.state.angles)


def base_env_of(env):
    """The env inside any TorchRL transforms around it (``TransformedEnv.base_env``), or ``env``."""
    return getattr(env, "base_env", env)


def reset_at(env, start: TensorDictBase) -> TensorDictBase:
    """``env.reset(start)`` that brings ``init_angles`` (B, 4) radians and ``init_K`` (B,) to the
    cavities through any transforms around the ``LaserCavityEnv``: TorchRL's ``TransformedEnv``
    passes on only the reset and state keys of its input, so the start is handed to the base env
    for this reset, and the transforms (e.g. the stacked history) reset with it."""
    base = base_env_of(env)
    if base is env:
        return env.reset(start)
    base._start = start.select("init_angles", "init_K", strict=False)
    try:
        return env.reset(start.exclude("init_angles", "init_K"))
    finally:
        base._start = None
