"""Accuracy of the batched torch solver against the stored DOP853 reference solutions."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from laserrl.physics import CavityParams, reference, reward_terms, round_trip, run_to_convergence
from laserrl.physics.cavity import propagate
from laserrl.physics.jones import apply_jones, cavity_jones

SETTINGS = {
    # name: (params, dtype, max relative L2 error per round trip)
    "default-complex64": (CavityParams(), torch.complex64, 1e-4),
    "default-complex128": (CavityParams(), torch.complex128, 1e-4),
    "dop853-complex64": (CavityParams(integrator="dop853", z_steps=4), torch.complex64, 1e-4),
    "precise-complex128": (CavityParams.precise(), torch.complex128, 1e-8),
}


@pytest.mark.parametrize("setting", list(SETTINGS))
def test_one_round_trip_matches_reference(ref_case, setting, rel_err):
    params, dtype, tol = SETTINGS[setting]
    c = ref_case
    j = c.rounds - 1  # round trips u[j] -> u[j+1], j = 0 .. rounds-2, all in one batch
    u = torch.as_tensor(c.u[:-1]).to(dtype)
    v = torch.as_tensor(c.v[:-1]).to(dtype)
    angles = torch.as_tensor(c.angles_rad).expand(j, 4)
    K = torch.full((j,), c.K)
    u1, v1 = round_trip(u, v, angles, K, params)
    assert u1.shape == (j, params.n) and u1.dtype == dtype and v1.dtype == dtype
    err = rel_err(u1, v1, c.u[1:], c.v[1:])
    assert err.shape == (j,)
    assert np.all(np.isfinite(err))
    assert err.max() <= tol, f"{c.name}: worst round trip {int(err.argmax())} has error {err.max():.3g} > {tol:g}"


@pytest.mark.parametrize("case", ["siso_modelock", "noise_start"])
def test_split_step_is_fourth_order(ref_cases, case, rel_err):
    """Strang + one Richardson extrapolation: doubling z_steps cuts the error about 16x.
    (Without refinement, so that the fixed scheme itself is measured.)"""
    c = ref_cases[case]
    u = torch.as_tensor(c.u[:-1])
    v = torch.as_tensor(c.v[:-1])
    angles = torch.as_tensor(c.angles_rad).expand(len(u), 4)
    errors = []
    for steps in (8, 16):
        p = CavityParams(z_steps=steps)
        u1, v1 = propagate(u, v, c.K, p, refine=False)
        u1, v1 = apply_jones(cavity_jones(angles, u1.dtype), u1, v1)
        errors.append(rel_err(u1, v1, c.u[1:], c.v[1:]).max())
    assert errors[0] / errors[1] > 10.0, errors


def test_modelock_run_to_convergence_matches_reference(ref_cases):
    c = ref_cases["siso_modelock"]
    params = CavityParams.precise()
    u0 = torch.as_tensor(c.u0, dtype=torch.complex128)[None]
    v0 = torch.as_tensor(c.v0, dtype=torch.complex128)[None]
    angles = torch.as_tensor(c.angles_rad)[None]
    res = run_to_convergence(u0, v0, angles, c.K, params, tol=1e-6, max_round_trips=500)
    assert bool(res.converged[0])
    assert 1 < int(res.round_trips[0]) < 500
    assert float(res.change[0]) < 1e-6
    _, _, r = reward_terms(res.u, res.v, params)
    assert float(r[0]) == pytest.approx(c.r, rel=1e-3)
    for got, want in ((res.u[0], c.u[-1]), (res.v[0], c.v[-1])):
        mod, mod_ref = np.abs(got.numpy()), np.abs(want)
        assert np.linalg.norm(mod - mod_ref) / np.linalg.norm(mod_ref) <= 1e-3


@pytest.mark.parametrize("j", [0, 20])
def test_reference_solver_reproduces_stored_round_trips(ref_cases, j, rel_err):
    c = ref_cases["siso_modelock"]
    u1, v1 = reference.round_trip(c.u[j], c.v[j], c.angles_rad, c.K, CavityParams(), rtol=1e-10, atol=1e-12)
    assert u1.shape == (256,) and v1.shape == (256,)
    assert rel_err(u1, v1, c.u[j + 1], c.v[j + 1]) <= 1e-8


def test_reference_reward_terms_equal_stored(ref_case):
    c = ref_case
    E, M4, r = reference.reward_terms(c.u[-1], c.v[-1], CavityParams())
    assert E == pytest.approx(c.E, rel=1e-10)
    assert M4 == pytest.approx(c.M4, rel=1e-10)
    assert r == pytest.approx(c.r, rel=1e-10)
