"""Reward terms (E, M4, r) and the convergence measure."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from laserrl.physics import amplitude, convergence, reference, reward_terms, sech_fields

FAST = settings(max_examples=20, deadline=None)


def test_reward_terms_equal_stored_values(ref_case, params):
    c = ref_case
    u = torch.as_tensor(c.u[-1:])
    v = torch.as_tensor(c.v[-1:])
    E, M4, r = reward_terms(u, v, params)
    assert E.dtype == torch.float64 and E.shape == (1,)
    assert float(E[0]) == pytest.approx(c.E, rel=1e-6)
    assert float(M4[0]) == pytest.approx(c.M4, rel=1e-6)
    assert float(r[0]) == pytest.approx(c.r, rel=1e-6)
    ref = reference.reward_terms(c.u[-1], c.v[-1], params)
    np.testing.assert_allclose([float(E[0]), float(M4[0]), float(r[0])], ref, rtol=1e-10)


def test_reward_terms_are_per_cavity(ref_cases, params):
    cases = list(ref_cases.values())
    u = torch.as_tensor(np.stack([c.u[-1] for c in cases]))
    v = torch.as_tensor(np.stack([c.v[-1] for c in cases]))
    _, _, r = reward_terms(u, v, params)
    np.testing.assert_allclose(r.numpy(), [c.r for c in cases], rtol=1e-6)


@FAST
@given(a=st.floats(0.05, 3.0), split=st.floats(0.0, math.pi / 2))
def test_pulse_beats_plane_wave(params, a, split):
    # u, v share the amplitude a between the two polarizations; phi only sees a
    cs, sn = math.cos(split), math.sin(split)
    plane = torch.full((1, params.n), a, dtype=torch.complex128)
    pu, _ = sech_fields(1, params, amplitude=a, width=2.0, dtype=torch.complex128)
    u = torch.cat([plane * cs, pu * cs])
    v = torch.cat([plane * sn, pu * sn])
    E, M4, r = reward_terms(u, v, params)
    assert torch.isfinite(r).all() and (r > 0).all()
    assert r[1] > r[0]
    assert M4[1] < M4[0]  # a single spectral line is maximally peaked


@FAST
@given(scale=st.floats(0.1, 10.0), theta=st.floats(-math.pi, math.pi), phase=st.floats(-math.pi, math.pi))
def test_reward_terms_scale_and_polarization_rotation(ref_cases, params, scale, theta, phase):
    c = ref_cases["noise_start"]
    u = torch.as_tensor(c.u[-1:])
    v = torch.as_tensor(c.v[-1:])
    E, M4, r = reward_terms(u, v, params)
    rot = complex(math.cos(phase), math.sin(phase))
    u2 = scale * rot * (math.cos(theta) * u - math.sin(theta) * v)
    v2 = scale * rot * (math.sin(theta) * u + math.cos(theta) * v)
    E2, M42, r2 = reward_terms(u2, v2, params)
    torch.testing.assert_close(M42, M4, rtol=1e-9, atol=0)  # kurtosis ignores scale and polarization
    torch.testing.assert_close(E2, scale * E, rtol=1e-9, atol=0)
    torch.testing.assert_close(r2, scale * r, rtol=1e-9, atol=0)


@pytest.mark.parametrize("dtype", [torch.complex64, torch.complex128])
def test_zero_field_has_zero_reward_without_nan(params, dtype):
    z = torch.zeros(2, params.n, dtype=dtype)
    u = z.clone()
    u[1] = 0.3  # a non-zero neighbour must not be affected
    E, M4, r = reward_terms(z, z, params)
    assert not torch.isnan(E).any() and not torch.isnan(M4).any() and not torch.isnan(r).any()
    assert (r == 0).all() and (E == 0).all()
    E, M4, r = reward_terms(u, z, params)
    assert r[0] == 0 and not torch.isnan(r).any()
    assert float(E[1]) == pytest.approx(0.3 * math.sqrt(params.T - params.dt), rel=1e-5)


def test_amplitude_is_the_combined_modulus():
    u = torch.tensor([[3 + 4j, 0j]], dtype=torch.complex128)
    v = torch.tensor([[0j, 1 - 1j]], dtype=torch.complex128)
    torch.testing.assert_close(amplitude(u, v), torch.tensor([[5.0, math.sqrt(2)]], dtype=torch.float64))


def test_convergence_is_zero_for_identical_fields(ref_cases):
    c = ref_cases["miso_start"]
    u, v = torch.as_tensor(c.u[-3:]), torch.as_tensor(c.v[-3:])
    d = convergence(u, v, u.clone(), v.clone())
    assert d.shape == (3,)
    assert (d == 0).all()


@FAST
@given(eps=st.floats(-0.9, 2.0), j=st.integers(0, 29))
def test_convergence_of_scaled_field_is_eps(ref_cases, eps, j):
    c = ref_cases["noise_start"]
    u, v = torch.as_tensor(c.u[j : j + 1]), torch.as_tensor(c.v[j : j + 1])
    d = convergence((1 + eps) * u, (1 + eps) * v, u, v)
    # norm(phi (1 + eps) - phi) / norm(phi) = |eps|
    assert float(d[0]) == pytest.approx(abs(eps), rel=1e-9, abs=1e-12)


def test_convergence_matches_stored_change(ref_case):
    c = ref_case
    u, v = torch.as_tensor(c.u), torch.as_tensor(c.v)
    d = convergence(u[1:], v[1:], u[:-1], v[:-1])
    np.testing.assert_allclose(d.numpy(), c.change, rtol=1e-6)


def test_convergence_is_not_phase_sensitive_but_is_shape_sensitive(ref_cases):
    c = ref_cases["siso_modelock"]
    u, v = torch.as_tensor(c.u[-1:]), torch.as_tensor(c.v[-1:])
    assert float(convergence(1j * u, -v, u, v)[0]) == pytest.approx(0.0, abs=1e-15)
    shifted = convergence(torch.roll(u, 5, -1), torch.roll(v, 5, -1), u, v)
    assert float(shifted[0]) > 1e-2
