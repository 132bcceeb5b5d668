"""Structural invariants of the Jones matrices and the propagation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from laserrl.physics import (apply_jones, cavity_jones, noise_fields, propagate, reference, round_trip, sech_fields,
                             trapezoid_energy)
from laserrl.physics.jones import HALF, POLARIZER, QUARTER, element

angle = st.floats(min_value=-4 * math.pi, max_value=4 * math.pi, allow_nan=False, allow_infinity=False)
angles4 = st.tuples(angle, angle, angle, angle)
FAST = settings(max_examples=25, deadline=None)


def _eye(batch=()):
    return torch.eye(2, dtype=torch.complex128).expand(*batch, 2, 2)


# ----------------------------------------------------------------------------- Jones matrices
@FAST
@given(alphas=st.lists(angle, min_size=1, max_size=5))
@pytest.mark.parametrize("eigen", [QUARTER, HALF], ids=["quarter", "half"])
def test_waveplates_are_unitary(eigen, alphas):
    m = element(torch.tensor(alphas, dtype=torch.float64), eigen, torch.complex128)
    assert m.shape == (len(alphas), 2, 2)
    torch.testing.assert_close(m @ m.mH, _eye((len(alphas),)), rtol=0, atol=1e-12)
    torch.testing.assert_close(m.mH @ m, _eye((len(alphas),)), rtol=0, atol=1e-12)


@FAST
@given(alpha=angle)
def test_polarizer_is_a_rank_one_hermitian_projector(alpha):
    p = element(torch.tensor(alpha, dtype=torch.float64), POLARIZER, torch.complex128)
    torch.testing.assert_close(p @ p, p, rtol=0, atol=1e-12)
    torch.testing.assert_close(p, p.mH, rtol=0, atol=1e-12)
    assert int(torch.linalg.matrix_rank(p)) == 1
    # it transmits the axis at angle alpha and blocks the orthogonal one
    axis = torch.tensor([math.cos(alpha), math.sin(alpha)], dtype=torch.complex128)
    ortho = torch.tensor([-math.sin(alpha), math.cos(alpha)], dtype=torch.complex128)
    torch.testing.assert_close(p @ axis, axis, rtol=0, atol=1e-12)
    torch.testing.assert_close(p @ ortho, torch.zeros(2, dtype=torch.complex128), rtol=0, atol=1e-12)


@FAST
@given(angles=angles4, which=st.integers(0, 3), turns=st.integers(-2, 2))
def test_cavity_jones_has_period_pi_in_every_angle(angles, which, turns):
    a = torch.tensor(angles, dtype=torch.float64)
    shifted = a.clone()
    shifted[which] += turns * math.pi
    torch.testing.assert_close(cavity_jones(shifted, torch.complex128), cavity_jones(a, torch.complex128), rtol=0, atol=1e-11)


@FAST
@given(angles=angles4)
def test_cavity_jones_matches_numpy_reference(angles):
    got = cavity_jones(torch.tensor(angles, dtype=torch.float64), torch.complex128).numpy()
    np.testing.assert_allclose(got, reference.jones_matrix(np.array(angles)), rtol=0, atol=1e-12)


@FAST
@given(seed=st.integers(0, 2**31 - 1), batch=st.integers(1, 4))
def test_apply_jones_matches_explicit_product(seed, batch):
    rng = np.random.default_rng(seed)
    m = rng.normal(size=(batch, 2, 2)) + 1j * rng.normal(size=(batch, 2, 2))
    u = rng.normal(size=(batch, 16)) + 1j * rng.normal(size=(batch, 16))
    v = rng.normal(size=(batch, 16)) + 1j * rng.normal(size=(batch, 16))
    u1, v1 = apply_jones(torch.as_tensor(m), torch.as_tensor(u), torch.as_tensor(v))
    for b in range(batch):
        for i in range(16):
            expected = m[b] @ np.array([u[b, i], v[b, i]])
            assert u1[b, i].item() == pytest.approx(expected[0], abs=1e-12)
            assert v1[b, i].item() == pytest.approx(expected[1], abs=1e-12)


# ----------------------------------------------------------------------------- propagation
def test_batch_equals_single_cavities(ref_cases, params, rel_err):
    names = ("siso_modelock", "miso_start", "k_neg")
    cases = [ref_cases[n] for n in names]
    u = torch.as_tensor(np.stack([c.u[3] for c in cases]))
    v = torch.as_tensor(np.stack([c.v[3] for c in cases]))
    angles = torch.as_tensor(np.stack([c.angles_rad for c in cases]))
    K = torch.tensor([c.K for c in cases], dtype=torch.float64)
    assert len(set(K.tolist())) == 3  # distinct K, and distinct angles
    ub, vb = round_trip(u, v, angles, K, params)
    for b in range(3):
        us, vs = round_trip(u[b : b + 1], v[b : b + 1], angles[b : b + 1], K[b : b + 1], params)
        assert rel_err(ub[b], vb[b], us[0], vs[0]) <= 1e-12
    # and the cavities really are different from one another
    assert rel_err(ub[0], vb[0], ub[1], vb[1]) > 1e-2


def test_complex64_and_complex128_agree(ref_cases, params, rel_err):
    cases = [ref_cases[n] for n in ("siso_modelock", "siso_planewave", "noise_start")]
    u = torch.as_tensor(np.stack([c.u[5] for c in cases]))
    v = torch.as_tensor(np.stack([c.v[5] for c in cases]))
    angles = torch.as_tensor(np.stack([c.angles_rad for c in cases]))
    K = torch.tensor([c.K for c in cases], dtype=torch.float64)
    u64, v64 = round_trip(u, v, angles, K, params)
    u32, v32 = round_trip(u.to(torch.complex64), v.to(torch.complex64), angles.float(), K.float(), params)
    assert u32.dtype == torch.complex64 and u64.dtype == torch.complex128
    assert rel_err(u32, v32, u64, v64).max() <= 1e-5


@settings(max_examples=10, deadline=None)
@given(amplitude=st.floats(0.2, 1.5), K=st.floats(-0.5, 0.5), phase=st.floats(0, 2 * math.pi))
def test_lossless_propagation_conserves_energy(params, amplitude, K, phase):
    p = params.replace(g0=0.0, Gamma=0.0)
    u, v = sech_fields(2, p, amplitude=amplitude, dtype=torch.complex128)
    v = v * complex(math.cos(phase), math.sin(phase)) * 0.7  # different polarization state per draw
    u1, v1 = propagate(u, v, K, p)
    e0 = trapezoid_energy(u.abs() ** 2 + v.abs() ** 2, p.dt)
    e1 = trapezoid_energy(u1.abs() ** 2 + v1.abs() ** 2, p.dt)
    torch.testing.assert_close(e1, e0, rtol=1e-5, atol=0)
    # the propagation did do something (Kerr + dispersion change the fields)
    assert (u1 - u).abs().max() > 1e-3


@settings(max_examples=10, deadline=None)
@given(K=st.floats(-0.5, 0.5), j=st.integers(0, 20))
def test_swapping_u_v_and_negating_K_commutes_with_propagate(ref_cases, params, rel_err, K, j):
    c = ref_cases["noise_start"]  # u != v, so the swap is not trivial
    u = torch.as_tensor(c.u[j : j + 1]).to(torch.complex64)
    v = torch.as_tensor(c.v[j : j + 1]).to(torch.complex64)
    u1, v1 = propagate(u, v, K, params)
    v2, u2 = propagate(v, u, -K, params)
    assert rel_err(u2, v2, u1, v1)[0] <= 1e-5


@pytest.mark.filterwarnings("ignore:Torchinductor does not support code generation for complex operators")
def test_compiled_propagate_equals_eager(ref_cases, params, rel_err):
    """The only test with compile=True (compilation is a one-off cost per process). The two
    white-noise starts are refined with 4x the steps, through the same compiled graphs."""
    cases = [ref_cases[n] for n in ("siso_modelock", "noise_start")]
    u_n, v_n = noise_fields(2, params, generator=torch.Generator().manual_seed(3))
    u = torch.cat([torch.as_tensor(np.stack([c.u[2] for c in cases])).to(torch.complex64), u_n])
    v = torch.cat([torch.as_tensor(np.stack([c.v[2] for c in cases])).to(torch.complex64), v_n])
    K = torch.tensor([0.1, -0.05, 0.4, -0.2])
    ue, ve = propagate(u, v, K, params)
    uc, vc = propagate(u, v, K, params, compile=True)
    assert uc.dtype == torch.complex64 and uc.shape == ue.shape
    assert rel_err(uc, vc, ue, ve).max() <= 1e-5
    unrefined = propagate(u[2:], v[2:], K[2:], params, compile=True, refine=False)
    assert rel_err(*unrefined, uc[2:], vc[2:]).min() > 5e-5  # the compiled run did refine the noise
