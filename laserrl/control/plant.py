"""The controlled plant: B cavities of ``LaserCavityEnv`` driven by continuous angle commands.

Every controller of ``laserrl.control`` (deep RL included) acts through the same two
calls: ``set_K`` (the scenario's disturbance for this step) and ``step(angles_deg)``
(put the plates at these angles, then run the cavity for one agent step). A step is the
env's own: its ``hold`` action after ``set_angles``, so the round trips per step, the
convergence tolerance, dtype and physics are those of the env config (for a DQN, the
checkpoint's training env), and the observation is the env's own, which is exactly what
a DQN actor was trained on. For a DQN, ``angles + action_to_deltas(action)`` followed by a
hold step is the same transition as the env's step with that action.

``Plates`` makes the motorised waveplates imperfect. The controllers read back their own
commands (a stepper's count), as an experiment does, not where the plates are. A plate with
play (backlash) b moves only once the command c is more than b / 2 beyond it, and then
follows b / 2 behind (the play operator of a geared mount),

    p_t = c_t - b/2   if c_t - p_{t-1} >  b/2
    p_t = c_t + b/2   if c_t - p_{t-1} < -b/2
    p_t = p_{t-1}     otherwise,

and a plate that is moved lands with a Gaussian error: theta_t = p_t + sigma xi_t, xi_t ~ N(0, 1)
(a plate not moved stays where it is). Angle differences are taken modulo 180 deg.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import torch
from tensordict import TensorDict

from laserrl.envs.actions import hold_action
from laserrl.envs.factory import make_env
from laserrl.envs.laser_env import _spread, base_env_of, reset_at
from laserrl.envs.step import draw_cavities, wrap_angle


def _wrap_deg(x: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(wrap_angle(torch.deg2rad(x)))


@dataclass(frozen=True)
class Plates:
    """How the plates answer a command: ``backlash_deg`` (b, the play) and ``noise_deg`` (sigma,
    the standard deviation of where a moved plate lands), both >= 0; 0 and 0: exact plates."""

    noise_deg: float = 0.0
    backlash_deg: float = 0.0

    def __post_init__(self):
        from laserrl.validate import check_number

        check_number(self.noise_deg, "plates.noise_deg", low=0)
        check_number(self.backlash_deg, "plates.backlash_deg", low=0, high=90)

    @property
    def exact(self) -> bool:
        return self.noise_deg == 0 and self.backlash_deg == 0

    def follow(self, position: torch.Tensor, command: torch.Tensor, previous: torch.Tensor,
               generator: torch.Generator) -> torch.Tensor:
        """Where the plates are, (B, 4) deg, after ``command`` following ``previous`` from
        ``position`` (the play operator, then the landing error of the plates that moved)."""
        half = self.backlash_deg / 2
        gap = _wrap_deg(command - position)
        lagged = torch.where(gap > half, command - half, torch.where(gap < -half, command + half, position))
        moved = _wrap_deg(command - previous).abs() > 1e-9
        noise = torch.randn(command.shape, generator=generator, dtype=command.dtype) * self.noise_deg
        return _wrap_deg(torch.where(moved, lagged + noise.to(command.device), position))


class CavityPlant:
    """B cavities; angles in degrees (alpha1, alpha2, alpha3, alpha_p), K per cavity.

    Args:
        env_cfg: the ``env`` config (round trips per step, dtype, physics).
        controlled: names of the angles the DQN controls (sets the env's action spec).
        num_cavities: B.  steps: length of the run (the env's episode length).
        init_fields: "sech" or "noise" initial fields.  seed: the env's generator seed.
        plates: how the plates answer commands (``Plates``; default exact). The plates' noise
            is drawn from its own generator, seeded by ``seed``.
        physics_spread: None (the cavity the config names), or cavities other than it: D, E0,
            tau, g0, Gamma each drawn within +-fraction (one number, or one per parameter) of
            it, ``num_cavities // copies`` cavities from a generator seeded by ``seed``, repeated
            ``copies`` times (one copy per controller, so that all face the same cavities).
    """

    def __init__(self, env_cfg: Mapping[str, Any], controlled, num_cavities: int, steps: int, seed: int = 0,
                 init_fields: str = "sech", device: str = "cpu", plates: Plates = Plates(),
                 physics_spread=None, copies: int = 1):
        stage = {"controlled": list(controlled), "steps_deg": [2.0] * len(controlled), "init_fields": init_fields}
        spread = _spread(physics_spread)  # not the model's training spread: the cavities this run faces
        env_cfg = {**dict(env_cfg), "physics_spread": None if spread is None else physics_spread}
        self.env = make_env(env_cfg, stage, num_cavities, seed, device=device, centred=False, max_steps=steps)
        self.num_cavities = num_cavities
        self.cavities = None  # (num_cavities, 5) D, E0, tau, g0, Gamma of every cavity, or None: the nominal one
        if spread is not None:
            if num_cavities % copies:
                raise ValueError(f"num_cavities ({num_cavities}) must be a multiple of copies ({copies})")
            draw = draw_cavities(base_env_of(self.env).params, spread, num_cavities // copies,
                                 torch.Generator().manual_seed(int(seed) + 104729), device=self.env.device)
            self.cavities = draw.repeat(copies, 1)
        self._hold = torch.full((num_cavities,), hold_action(len(controlled)), dtype=torch.int64, device=self.env.device)
        self.obs: TensorDict | None = None
        self.plates = plates
        self._plate_rng = torch.Generator().manual_seed(int(seed) + 7919)  # its own stream, apart from the env's
        self.commanded: torch.Tensor | None = None  # (B, 4) deg: what the controllers set and read back

    def reset(self, angles_deg: torch.Tensor, K: torch.Tensor) -> TensorDict:
        """Fresh initial fields at these angles (B, 4) and K (B,); returns the observation."""
        td = TensorDict(init_angles=torch.deg2rad(angles_deg.to(torch.float64)), init_K=K.to(torch.float64),
                        batch_size=[self.num_cavities])
        self.obs = reset_at(self.env, td)
        if self.cavities is not None:  # the run's cavities in place of the env's own draw (drawn after
            # the initial fields, which do not depend on them)
            base_env_of(self.env).state.cavity = self.cavities.clone()
        self.commanded = self.true_angles_deg
        return self.obs

    def set_K(self, K: torch.Tensor) -> None:
        self.env.set_K(K)

    def step(self, angles_deg: torch.Tensor) -> TensorDict:
        """Put the plates at ``angles_deg`` (B, 4) and run one agent step; returns the
        observation (``fields``, ``angles``, ``r``, ``round_trips``)."""
        command = _wrap_deg(angles_deg.to(torch.float64).to(self.env.device))
        if self.plates.exact:
            self.env.set_angles(torch.deg2rad(command))
        else:  # the observations show the commands, as the controllers read them back
            where = self.plates.follow(self.true_angles_deg, command, self.commanded, self._plate_rng)
            self.env.set_angles(torch.deg2rad(where), reported=torch.deg2rad(command))
        self.commanded = command
        td = self.env.step(self.obs.exclude("done", "terminated", "truncated").set("action", self._hold))
        self.obs = td["next"].exclude("done", "terminated", "truncated")
        return self.obs

    @property
    def angles_deg(self) -> torch.Tensor:
        """The angles (B, 4) the controllers last set, in degrees, float64, wrapped to [-90, 90)
        (with exact plates, where the plates are)."""
        return self.commanded.clone() if self.commanded is not None else self.true_angles_deg

    @property
    def true_angles_deg(self) -> torch.Tensor:
        """Where the plates are (B, 4) in degrees, float64, wrapped to [-90, 90)."""
        return self.env.angles_deg().to(torch.float64)

    @property
    def r(self) -> torch.Tensor:
        return self.obs["r"].squeeze(-1).to(torch.float64)

