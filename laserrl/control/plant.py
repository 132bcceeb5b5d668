"""The controlled plant: B cavities of ``LaserCavityEnv`` driven by continuous angle commands.

Every controller of ``laserrl.control`` (deep RL included) acts through the same two
calls: ``set_K`` (the scenario's disturbance for this step) and ``step(angles_deg)``
(put the plates at these angles, then run the cavity for one agent step). A step is the
env's own: its ``hold`` action after ``set_angles``, so the round trips per step, the
convergence tolerance, dtype and physics are those of the env config (for a DQN, the
checkpoint's training env), and the observation is the env's own, which is exactly what
a DQN actor was trained on. For a DQN, ``angles + action_to_deltas(action)`` followed by a
hold step is the same transition as the env's step with that action.
"""
from __future__ import annotations

from typing import Any, Mapping

import torch
from tensordict import TensorDict

from laserrl.envs.actions import hold_action
from laserrl.envs.factory import make_env


class CavityPlant:
    """B cavities; angles in degrees (alpha1, alpha2, alpha3, alpha_p), K per cavity.

    Args:
        env_cfg: the ``env`` config (round trips per step, dtype, physics).
        controlled: names of the angles the DQN controls (sets the env's action spec).
        num_cavities: B.  steps: length of the run (the env's episode length).
        init_fields: "sech" or "noise" initial fields.  seed: the env's generator seed.
    """

    def __init__(self, env_cfg: Mapping[str, Any], controlled, num_cavities: int, steps: int, seed: int = 0,
                 init_fields: str = "sech", device: str = "cpu"):
        stage = {"controlled": list(controlled), "steps_deg": [2.0] * len(controlled), "init_fields": init_fields}
        self.env = make_env(dict(env_cfg), stage, num_cavities, seed, device=device, centred=False, max_steps=steps)
        self.num_cavities = num_cavities
        self._hold = torch.full((num_cavities,), hold_action(len(controlled)), dtype=torch.int64, device=self.env.device)
        self.obs: TensorDict | None = None

    def reset(self, angles_deg: torch.Tensor, K: torch.Tensor) -> TensorDict:
        """Fresh initial fields at these angles (B, 4) and K (B,); returns the observation."""
        td = TensorDict(init_angles=torch.deg2rad(angles_deg.to(torch.float64)), init_K=K.to(torch.float64),
                        batch_size=[self.num_cavities])
        self.obs = self.env.reset(td)
        return self.obs

    def set_K(self, K: torch.Tensor) -> None:
        self.env.set_K(K)

    def step(self, angles_deg: torch.Tensor) -> TensorDict:
        """Put the plates at ``angles_deg`` (B, 4) and run one agent step; returns the
        observation (``fields``, ``angles``, ``r``, ``round_trips``)."""
        self.env.set_angles(torch.deg2rad(angles_deg.to(torch.float64)))
        td = self.env.step(self.obs.exclude("done", "terminated", "truncated").set("action", self._hold))
        self.obs = td["next"].exclude("done", "terminated", "truncated")
        return self.obs

    @property
    def angles_deg(self) -> torch.Tensor:
        """Current angles (B, 4) in degrees, float64, wrapped to [-90, 90)."""
        return self.env.angles_deg()

    @property
    def r(self) -> torch.Tensor:
        return self.obs["r"].squeeze(-1).to(torch.float64)

