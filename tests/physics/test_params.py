"""CavityParams: paper defaults, validation and the grid."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from laserrl.physics import CavityParams

FLOAT_FIELDS = ("D", "E0", "tau", "g0", "Gamma", "A", "B", "Z", "T")


def test_defaults_are_the_papers_values(ref_params):
    p = CavityParams()
    assert set(ref_params) == {"D", "E0", "tau", "g0", "Gamma", "A", "B", "Z", "T", "n"}
    for name, value in ref_params.items():
        assert getattr(p, name) == value, name


def test_float_fields_list_is_complete():
    # the NaN parametrisation below must cover every float field of the dataclass
    floats = {f.name for f in dataclasses.fields(CavityParams) if f.type in (float, "float")}
    assert floats == set(FLOAT_FIELDS)


@pytest.mark.parametrize(
    "field, value",
    [
        ("n", 100),
        ("n", 8),
        ("n", 0),
        ("T", 0.0),
        ("T", -60.0),
        ("Z", 0.0),
        ("Z", -1.5),
        ("E0", 0.0),
        ("E0", -4.23),
        ("tau", -0.1),
    ],
)
def test_invalid_value_raises_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"CavityParams\.{field}\b"):
        CavityParams(**{field: value})


@pytest.mark.parametrize("field", FLOAT_FIELDS)
def test_nan_raises_naming_the_field(field):
    with pytest.raises(ValueError, match=rf"CavityParams\.{field}\b"):
        CavityParams(**{field: float("nan")})


@settings(max_examples=20, deadline=None)
@given(n=st.integers(min_value=1, max_value=5000))
def test_n_accepted_iff_power_of_two_at_least_16(n):
    ok = n >= 16 and (n & (n - 1)) == 0
    if ok:
        assert CavityParams(n=n).n == n
    else:
        with pytest.raises(ValueError, match=r"CavityParams\.n\b"):
            CavityParams(n=n)


def test_precise_changes_numerics_only():
    default, precise = CavityParams(), CavityParams.precise()
    assert (precise.integrator, precise.z_steps) == ("dop853", 32)
    for f in dataclasses.fields(CavityParams):
        if f.name not in ("z_steps", "integrator"):
            assert getattr(precise, f.name) == getattr(default, f.name), f.name
    # overrides are passed through
    assert CavityParams.precise(T=30.0).T == 30.0


def test_params_are_frozen_and_hashable():
    p = CavityParams()
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.D = 0.0  # type: ignore[misc]
    assert hash(p) == hash(CavityParams())
    assert p.replace(D=-0.2).D == -0.2 and p.D == -0.4


def test_time_grid_equals_reference(ref_npz):
    p = CavityParams()
    t = p.time_grid()
    assert t.dtype == torch.float64 and t.shape == (p.n,)
    np.testing.assert_allclose(t.numpy(), ref_npz["t"], rtol=0, atol=1e-12)
    assert p.dt == pytest.approx(float(ref_npz["t"][1] - ref_npz["t"][0]), rel=1e-12)


def test_wavenumbers_equal_fftfreq():
    p = CavityParams()
    k = p.wavenumbers()
    expected = 2 * math.pi / p.T * np.fft.fftfreq(p.n, 1.0 / p.n)
    assert k.dtype == torch.float64
    np.testing.assert_allclose(k.numpy(), expected, rtol=1e-14, atol=1e-14)


def test_whole_float_n_and_z_steps_become_ints():
    """Config files may give 256.0: it is taken as the integer, and a fraction is refused."""
    p = CavityParams(n=256.0, z_steps=4.0)
    assert (p.n, p.z_steps) == (256, 4) and type(p.n) is int and type(p.z_steps) is int
    assert p == CavityParams(n=256, z_steps=4)
    assert p.time_grid().shape == (256,) and p.wavenumbers().shape == (256,)
    with pytest.raises(ValueError, match=r"CavityParams\.n must be a power of two"):
        CavityParams(n=256.5)
    with pytest.raises(ValueError, match=r"CavityParams\.z_steps must be a positive integer"):
        CavityParams(z_steps=4.5)


def test_unknown_integrator_is_named():
    with pytest.raises(ValueError, match=r"CavityParams\.integrator"):
        CavityParams(integrator="rk4")


def test_split_integrator_needs_isotropic_kerr_coefficients():
    # the exact Kerr flow of the split-step scheme exists only for A + B = 1
    with pytest.raises(ValueError, match=r"integrator='split' needs A \+ B = 1"):
        CavityParams(A=0.5, B=0.2)
    assert CavityParams(A=0.5, B=0.2, integrator="dop853").A == 0.5
    assert CavityParams(A=0.5, B=0.5).integrator == "split"


def test_split_passes_default_explicit_and_refined():
    assert CavityParams().split_passes == (10, 16)  # ceil(5 z_steps / 4) and 2 z_steps
    assert [CavityParams(z_steps=z).split_passes for z in (1, 2, 4, 16)] == [(1, 2), (3, 4), (5, 8), (20, 32)]
    old = CavityParams(z_steps_coarse=8.0)  # whole floats from config files become ints
    assert old.split_passes == (8, 16) and type(old.z_steps_coarse) is int
    assert CavityParams().refined(4).split_passes == (40, 64) and old.refined(4).split_passes == (32, 64)


@pytest.mark.parametrize("kwargs", [dict(z_steps_coarse=16), dict(z_steps_coarse=0), dict(z_steps_coarse=9.5),
                                    dict(z_steps_coarse=8, integrator="dop853"), dict(z_steps_coarse="8")])
def test_invalid_coarse_pass_is_named(kwargs):
    with pytest.raises(ValueError, match=r"CavityParams\.z_steps_coarse\b"):
        CavityParams(**kwargs)
