"""A synthetic plant with a known smooth objective, for fast controller tests."""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict


class BumpPlant:
    """Duck-types ``CavityPlant``: r = peak exp(-sum_j ((angle_j - optimum_j - drift K) / width)^2 / 2)
    over the controlled angles (degrees), answered at once, no fields."""

    def __init__(self, num_cavities, optimum_deg, controlled_idx=(0,), width_deg=15.0, peak=0.2, K_shift_deg=0.0,
                 round_trips=7):
        self.num_cavities = num_cavities
        self.optimum = torch.as_tensor(optimum_deg, dtype=torch.float64).reshape(-1, len(controlled_idx)).expand(
            num_cavities, len(controlled_idx)).clone()
        self.idx = list(controlled_idx)
        self.width, self.peak, self.K_shift = width_deg, peak, K_shift_deg
        self.round_trips = round_trips
        self._angles = torch.zeros(num_cavities, 4, dtype=torch.float64)
        self._K = torch.zeros(num_cavities, dtype=torch.float64)
        self.steps = 0

    def objective(self, angles):
        d = (angles[:, self.idx] - self.optimum - self.K_shift * self._K[:, None]) / self.width
        return self.peak * torch.exp(-0.5 * (d**2).sum(-1))

    def _obs(self):
        r = self.objective(self._angles)
        return TensorDict(fields=torch.zeros(self.num_cavities, 4, 8), angles=torch.deg2rad(self._angles).float(),
                          r=r.float()[:, None],
                          round_trips=torch.full((self.num_cavities, 1), self.round_trips, dtype=torch.int64),
                          batch_size=[self.num_cavities])

    def reset(self, angles_deg, K):
        self._angles = angles_deg.clone().to(torch.float64)
        self._K = K.clone().to(torch.float64)
        self.obs = self._obs()
        return self.obs

    def set_K(self, K):
        self._K = K.clone().to(torch.float64)

    def step(self, angles_deg):
        self._angles = angles_deg.clone().to(torch.float64)
        self.steps += 1
        self.obs = self._obs()
        return self.obs

    @property
    def angles_deg(self):
        return self._angles.clone()

    true_angles_deg = angles_deg  # exact plates

    @property
    def r(self):
        return self.obs["r"].squeeze(-1).double()


def start_angles(alpha1_deg, num_cavities):
    a = np.tile([0.0, 3.0, 28.0, 88.0], (num_cavities, 1))
    a[:, 0] = alpha1_deg
    return a
