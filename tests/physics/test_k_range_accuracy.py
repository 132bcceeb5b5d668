"""One-round-trip accuracy of the default solver at the ends of the K range, from sech and noise
starts, against precise DOP853 trajectories (``laserrl-bench --k-sweep`` runs the full sweep)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from laserrl.bench import one_round_trip_errors, sweep_references
from laserrl.physics import CavityParams, noise_fields, sech_fields
from laserrl.physics.cavity import _propagate_fixed

#: The paper's single-input task at its start angle and at the low end of its alpha1 range.
ANGLES_DEG = {"alpha1=-24": (-24.0, 3.0, 28.0, 88.0), "alpha1=-40": (-40.0, 3.0, 28.0, 88.0)}


@pytest.fixture(scope="module")
def references():
    # 2 K x 2 angle sets x (sech, noise) cavities, 4 round trips each: the first round trip from
    # noise and the intense pulse of the second round trip from sech at K = 0.4 are the hardest
    return sweep_references(Ks=(-0.2, 0.4), angles_deg=ANGLES_DEG, round_trips=4, seed=0)


def test_default_one_round_trip_error_is_below_1e4_at_both_ends_of_the_k_range(references):
    labels = references[0]
    err = one_round_trip_errors(references, CavityParams(), dtype=torch.complex64)
    assert err.shape == (len(labels), 4) and np.all(np.isfinite(err))
    i, j = np.unravel_index(err.argmax(), err.shape)
    assert err.max() < 1e-4, f"{labels[i]}, round trip {j}: one-round-trip error {err.max():.3g}"


def test_white_noise_is_flagged_as_unresolved_and_smooth_fields_are_not():
    """White noise has power in modes the coarse pass does not resolve: its error estimate is
    infinite, so that ``propagate`` refines it. A sech start's estimate stays finite."""
    p = CavityParams()
    u_n, v_n = noise_fields(2, p, generator=torch.Generator().manual_seed(1))
    u_s, v_s = sech_fields(2, p)
    u, v = torch.cat([u_n, u_s]), torch.cat([v_n, v_s])
    _, _, error = _propagate_fixed(u, v, torch.tensor([0.4, -0.2, 0.4, -0.2]), p, False)
    assert [math.isinf(e) for e in error.tolist()] == [True, True, False, False]
    assert float(error[2:].max()) < 0.05
