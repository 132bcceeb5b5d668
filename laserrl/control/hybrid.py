"""Deep RL as a controller, and the hybrid: deep RL finds the lock, ESC holds it.

The hybrid's rule (per cavity, the paper's section 4):

* deep RL -> ESC when r >= ``lock_r`` for ``lock_steps`` consecutive steps; ESC starts
  from the current angles (estimates = angles, filters in the steady state of the
  current r). With ``settle_steps`` = w > 0, also only once the agent's climb has
  levelled off: r is no more than ``settle_rise`` (a fraction) above the highest r of the
  w steps before. The level alone is calibrated on one cavity (the instruments' reading
  for r = 0.15 there); on a cavity with more gain the same reading comes at a lower r, and
  ESC engaged on the level would hold a state that is not mode-locked. The agent climbs
  through that state, so waiting for the climb to end does not depend on the calibration;
* ESC -> deep RL when r < ``unlock_r`` for ``unlock_steps`` consecutive steps (the lock
  is lost, e.g. after a jump of K that ESC's local search cannot follow); with
  ``restart_memory`` a recurrent agent's memory restarts there, as at an episode's start.

Both counters restart at every switch. r is the reward the controllers read
(``laserrl.control.esc.observed_r``): the paper's r, or with measured observations the
instruments' r_measured, whose scale is its own (set ``lock_r`` and ``unlock_r`` in it).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from laserrl.control.checks import integer, is_finite_number
from laserrl.control.esc import ESCParams, ExtremumSeeking, observed_r
from laserrl.envs.actions import action_to_deltas
from laserrl.envs.laser_env import ANGLE_NAMES
from laserrl.envs.step import turn_steps

#: controller modes recorded per step (``mode`` in control.json and the plot)
MODE_RL, MODE_ESC = 0, 1


class DeepRL:
    """Greedy deep RL: ``policy`` maps the observation (``fields``, ``angles``) to a discrete
    ``action``; the angles move by ``action_to_deltas(action, steps_deg)`` as in the env.

    A recurrent policy (one that reads ``recurrent_state``, ``env.gru_size``) keeps its state
    here from one call to the next, from zero at ``reset`` and, per cavity, at ``restart(mask)``;
    it reads every step's observation, also while the hybrid's ESC moves the plates.

    With ``fine_steps_deg`` and ``fine_from_r``, the angles move by ``fine_steps_deg`` instead on the
    cavities whose reward read (``observed_r``) is >= ``fine_from_r``: coarse steps to search, fine
    ones near a lock."""

    name = "rl"

    def __init__(self, policy: Callable[[TensorDictBase], TensorDictBase], controlled, steps_deg,
                 fine_steps_deg=None, fine_from_r: float | None = None):
        for name, steps in (("steps_deg", steps_deg), ("fine_steps_deg", fine_steps_deg)):
            if steps is not None and len(steps) != len(controlled):
                raise ValueError(f"{name} needs one step per controlled angle {list(controlled)}, got {list(steps)}")
        if (fine_steps_deg is None) != (fine_from_r is None):
            raise ValueError("fine_steps_deg and fine_from_r go together (finer steps near a lock)")
        self.policy = policy
        self.idx = [ANGLE_NAMES.index(a) for a in controlled]
        self.steps = torch.tensor([float(s) for s in steps_deg], dtype=torch.float64)
        # near a lock (the reward read >= fine_from_r) the plates turn by fine_steps_deg instead
        self.fine_steps = None if fine_steps_deg is None else torch.tensor([float(s) for s in fine_steps_deg],
                                                                           dtype=torch.float64)
        self.fine_from_r = fine_from_r

        self._memory = None  # a recurrent policy's state after the last step (None: start afresh)

    def reset(self, obs, angles_deg) -> None:
        self._memory = None

    def restart(self, mask: torch.Tensor) -> None:
        """Restart the recurrent memory of the cavities in ``mask`` (a new search): the zero state
        an episode's first step starts from."""
        if self._memory is not None:
            mask = mask.to(self._memory.device).reshape(-1, *[1] * (self._memory.dim() - 1))
            self._memory = torch.where(mask, torch.zeros_like(self._memory), self._memory)

    def act(self, obs, angles_deg: torch.Tensor) -> torch.Tensor:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            keys = getattr(self.policy, "in_keys", None)  # a TensorDict module reads its own keys
            td = (obs if keys is None else obs.select(*keys, strict=False)).clone()
            recurrent = keys is not None and "recurrent_state" in keys
            if recurrent:
                first = self._memory is None  # the plant's env carries the state's shape (make_env's primer)
                td["recurrent_state"] = torch.zeros_like(td["recurrent_state"]) if first else self._memory
                td["is_init"] = torch.full((*td.batch_size, 1), first, dtype=torch.bool, device=td.device)
            out = self.policy(td)
            if recurrent:
                self._memory = out["next", "recurrent_state"]
            action = out["action"]
        command = angles_deg.clone().to(torch.float64)
        steps = self.steps.to(action.device)
        if self.fine_steps is not None:  # per cavity: the fine steps where the reward read reaches fine_from_r
            steps = turn_steps(steps, self.fine_steps.to(action.device), torch.from_numpy(observed_r(obs)).to(action.device),
                               self.fine_from_r)
        command[:, self.idx] += action_to_deltas(action.reshape(-1), steps).to(command)
        return command


@dataclass
class HybridRule:
    """Switching rule of the hybrid (see the module docstring)."""

    lock_r: float = 0.15
    lock_steps: int = 1
    unlock_r: float = 0.1
    unlock_steps: int = 3
    restart_memory: bool = False  # a recurrent agent's memory restarts when the lock is lost
    settle_steps: int = 0  # > 0: ESC engages only once r rose by at most settle_rise over these steps
    settle_rise: float = 0.02

    def __post_init__(self):
        for name in ("lock_r", "unlock_r", "settle_rise"):
            v = getattr(self, name)
            if not is_finite_number(v) or v < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
        for name in ("lock_steps", "unlock_steps"):
            integer(self, name, 1)
        integer(self, "settle_steps", 0)
        if not isinstance(self.restart_memory, bool):
            raise ValueError(f"restart_memory must be true or false, got {self.restart_memory!r}")
        if self.unlock_r > self.lock_r:
            raise ValueError(f"unlock_r ({self.unlock_r}) must be <= lock_r ({self.lock_r}), or the modes would chatter")


class Hybrid:
    """Deep RL until locked, then ESC; back to deep RL when the lock is lost (``HybridRule``)."""

    name = "hybrid"

    def __init__(self, rl: DeepRL, esc_params: ESCParams, rule: HybridRule, controlled, num_cavities: int):
        self.rl, self.rule = rl, rule
        self.esc = ExtremumSeeking(esc_params, controlled, num_cavities)
        self.mode = torch.full((num_cavities,), MODE_RL, dtype=torch.int64)
        self._above = torch.zeros(num_cavities, dtype=torch.int64)  # consecutive steps with r >= lock_r
        self._below = torch.zeros(num_cavities, dtype=torch.int64)  # consecutive steps with r < unlock_r
        self.switches = torch.zeros(num_cavities, dtype=torch.int64)
        # r of the last settle_steps steps (newest last); -inf before the first step: nothing to level off from
        self._recent = torch.full((num_cavities, rule.settle_steps), float("-inf"), dtype=torch.float64)

    def reset(self, obs, angles_deg) -> None:
        self.mode.fill_(MODE_RL)
        self._recent.fill_(float("-inf"))
        self._above.zero_()
        self._below.zero_()
        self.switches.zero_()
        self.rl.reset(obs, angles_deg)

    def act(self, obs, angles_deg: torch.Tensor) -> torch.Tensor:
        r = torch.from_numpy(observed_r(obs))
        self._above = torch.where(r >= self.rule.lock_r, self._above + 1, 0)
        self._below = torch.where(r < self.rule.unlock_r, self._below + 1, 0)
        esc = self.mode == MODE_ESC
        engage = ~esc & (self._above >= self.rule.lock_steps)
        if self.rule.settle_steps:
            # the climb has ended: r is not above the recent steps' best by more than settle_rise
            r64 = r.to(torch.float64)
            engage &= r64 <= (1 + self.rule.settle_rise) * self._recent.max(-1).values
            self._recent = torch.cat([self._recent[:, 1:], r64[:, None]], dim=1)
        release = esc & (self._below >= self.rule.unlock_steps)
        if bool(engage.any()):
            self.esc.reset(obs, angles_deg, engage)
        switched = engage | release
        self.mode = torch.where(engage, MODE_ESC, torch.where(release, MODE_RL, self.mode))
        self._above = torch.where(switched, 0, self._above)
        self._below = torch.where(switched, 0, self._below)
        self.switches += switched.long()
        if self.rule.restart_memory and bool(release.any()):
            self.rl.restart(release)
        # ESC runs for every cavity (its state is restarted on engagement), and is used where engaged
        cmd_esc = self.esc.act(obs, angles_deg)
        cmd_rl = self.rl.act(obs, angles_deg)
        return torch.where((self.mode == MODE_ESC)[:, None].to(cmd_rl.device), cmd_esc, cmd_rl)
