"""run_to_convergence: per-cavity bookkeeping, masking, errors and argument checks."""
from __future__ import annotations

import math
import warnings

import pytest
import torch

from laserrl.physics import (
    CavityParams,
    NonFiniteFieldError,
    check_finite,
    round_trip,
    run_to_convergence,
    sech_fields,
)

MODELOCK_DEG = (-24.0, 3.0, 28.0, 88.0)
PLANEWAVE_DEG = (-12.0, 3.0, 28.0, 88.0)


@pytest.fixture(scope="module")
def two_cavities():
    """Cavity 0 mode-locks (converges), cavity 1 stays a drifting plane wave."""
    params = CavityParams()
    u, v = sech_fields(2, params, dtype=torch.complex64)
    angles = torch.deg2rad(torch.tensor([MODELOCK_DEG, PLANEWAVE_DEG], dtype=torch.float64))
    K = torch.tensor([0.1, 0.1])
    res = run_to_convergence(u, v, angles, K, params, tol=1e-5, max_round_trips=60)
    return params, angles, K, res


def test_round_trip_counts_are_per_cavity(two_cavities):
    _, _, _, res = two_cavities
    assert res.round_trips.shape == (2,) and res.round_trips.dtype == torch.int64
    assert res.converged.tolist() == [True, False]
    assert int(res.round_trips[1]) == 60  # the plane wave hits the cap
    assert 1 < int(res.round_trips[0]) < 60
    assert float(res.change[0]) < 1e-5 <= float(res.change[1])
    assert res.tol == 1e-5


def test_inactive_cavity_is_left_bit_identical(two_cavities):
    params, angles, K, res = two_cavities
    u_before, v_before = res.u.clone(), res.v.clone()
    again = run_to_convergence(res.u, res.v, angles, K, params, tol=1e-5, max_round_trips=5,
                               active=torch.tensor([True, False]))
    assert torch.equal(again.u[1], u_before[1]) and torch.equal(again.v[1], v_before[1])
    assert again.round_trips.tolist()[1] == 0
    assert not bool(again.converged[1])
    # the converged cavity does run (one round trip is enough to see it is still converged)
    assert again.round_trips.tolist()[0] == 1 and bool(again.converged[0])
    assert not torch.equal(again.u[0], u_before[0])
    # the input tensors are not modified in place
    assert torch.equal(res.u, u_before) and torch.equal(res.v, v_before)


def test_result_fields_equal_repeated_round_trips(params):
    # a cavity that does not converge within the cap ran exactly max_round_trips round trips
    u, v = sech_fields(1, params, dtype=torch.complex128)
    angles = torch.deg2rad(torch.tensor([PLANEWAVE_DEG], dtype=torch.float64))
    res = run_to_convergence(u, v, angles, 0.1, params, tol=0.0, max_round_trips=3)
    for _ in range(3):
        u, v = round_trip(u, v, angles, 0.1, params)
    torch.testing.assert_close(res.u, u, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(res.v, v, rtol=1e-12, atol=1e-14)
    assert res.round_trips.tolist() == [3] and res.converged.tolist() == [False]


def _batch_with_nan(params, index=1, batch=3):
    u, v = sech_fields(batch, params, dtype=torch.complex64)
    u[index, 17] = complex(float("nan"), 0.0)
    return u, v


def test_check_finite_names_the_cavity(params):
    u, v = _batch_with_nan(params)
    with pytest.raises(NonFiniteFieldError, match=r"cavity 1\b") as info:
        check_finite(u, v)
    assert info.value.cavities == [1]
    assert isinstance(info.value, FloatingPointError)
    check_finite(*sech_fields(3, params))  # finite fields pass


def test_check_finite_lists_all_bad_cavities(params):
    u, v = sech_fields(4, params, dtype=torch.complex128)
    v[3, 0] = complex(0.0, float("inf"))
    u[0, 5] = complex(float("nan"), float("nan"))
    with pytest.raises(NonFiniteFieldError) as info:
        check_finite(u, v)
    assert info.value.cavities == [0, 3]


def test_run_to_convergence_raises_on_nan_cavity(params):
    u, v = _batch_with_nan(params)
    angles = torch.deg2rad(torch.tensor([MODELOCK_DEG] * 3))
    with pytest.raises(NonFiniteFieldError, match=r"cavity 1\b") as info:
        run_to_convergence(u, v, angles, 0.1, params, tol=1e-5, max_round_trips=3)
    assert info.value.cavities == [1]


def test_complex64_tolerance_floor_warns(params):
    u, v = sech_fields(1, params, dtype=torch.complex64)
    angles = torch.deg2rad(torch.tensor([MODELOCK_DEG]))
    with pytest.warns(UserWarning, match="complex128"):
        res = run_to_convergence(u, v, angles, 0.1, params, tol=1e-6, max_round_trips=2)
    assert res.tol == 1e-5


def test_complex128_resolves_paper_tolerance_without_warning(params):
    u, v = sech_fields(1, params, dtype=torch.complex128)
    angles = torch.deg2rad(torch.tensor([MODELOCK_DEG], dtype=torch.float64))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = run_to_convergence(u, v, angles, 0.1, params, tol=1e-6, max_round_trips=2)
    assert res.tol == 1e-6


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(tol=-1e-3), "tol"),
        (dict(tol=float("nan")), "tol"),
        (dict(max_round_trips=0), "max_round_trips"),
        (dict(max_round_trips=-5), "max_round_trips"),
        (dict(max_round_trips=2.5), "max_round_trips"),
    ],
)
def test_invalid_tol_or_max_round_trips(params, kwargs, name):
    u, v = sech_fields(1, params, dtype=torch.complex128)
    angles = torch.zeros(1, 4, dtype=torch.float64)
    with pytest.raises(ValueError, match=name):
        run_to_convergence(u, v, angles, 0.1, params, **kwargs)


def _good(params, batch=2, dtype=torch.complex64):
    u, v = sech_fields(batch, params, dtype=dtype)
    return dict(u=u, v=v, angles=torch.zeros(batch, 4), K=torch.zeros(batch))


@pytest.mark.parametrize(
    "change, pattern",
    [
        (lambda a, p: a.update(u=a["u"][:, :100]), r"field u\b"),
        (lambda a, p: a.update(v=a["v"][:1]), r"fields u and v"),
        (lambda a, p: a.update(u=a["u"][0]), r"field u\b"),
        (lambda a, p: a.update(v=a["v"][:, None, :]), r"field v\b"),
        (lambda a, p: a.update(u=a["u"].real.contiguous()), r"field u\b.*complex"),
        (lambda a, p: a.update(v=a["v"].abs()), r"field v\b.*complex"),
        (lambda a, p: a.update(u=a["u"].numpy()), r"field u\b"),
        (lambda a, p: a.update(v=a["v"].to(torch.complex128)), r"fields u and v"),
        (lambda a, p: a.update(K=torch.zeros(3)), r"\bK\b"),
        (lambda a, p: a.update(K=torch.zeros(2, 1)), r"\bK\b"),
        (lambda a, p: a.update(K=torch.zeros(2, dtype=torch.complex64)), r"\bK\b"),
        (lambda a, p: a.update(angles=torch.zeros(2, 3)), r"\bangles\b"),
        (lambda a, p: a.update(angles=torch.zeros(3, 4)), r"\bangles\b"),
        (lambda a, p: a.update(angles=torch.zeros(3)), r"\bangles\b"),
    ],
    ids=[
        "u-wrong-n", "v-wrong-batch", "u-1d", "v-3d", "u-real", "v-real", "u-numpy", "v-other-dtype",
        "K-wrong-batch", "K-2d", "K-complex", "angles-width-3", "angles-wrong-batch", "angles-vector-3",
    ],
)
@pytest.mark.parametrize("fn", ["run_to_convergence", "round_trip"])
def test_bad_arguments_raise_value_error_naming_them(params, change, pattern, fn):
    a = _good(params)
    change(a, params)
    with pytest.raises(ValueError, match=pattern):
        if fn == "run_to_convergence":
            run_to_convergence(a["u"], a["v"], a["angles"], a["K"], params, tol=1e-5, max_round_trips=1)
        else:
            round_trip(a["u"], a["v"], a["angles"], a["K"], params)


def test_scalar_K_and_single_angle_vector_broadcast(params):
    a = _good(params, dtype=torch.complex128)
    angles = torch.deg2rad(torch.tensor(MODELOCK_DEG, dtype=torch.float64))
    res_b = run_to_convergence(a["u"], a["v"], angles, 0.1, params, tol=0.0, max_round_trips=2)
    res_f = run_to_convergence(a["u"], a["v"], angles.expand(2, 4), torch.full((2,), 0.1, dtype=torch.float64),
                               params, tol=0.0, max_round_trips=2)
    torch.testing.assert_close(res_b.u, res_f.u, rtol=0, atol=0)
    assert math.isfinite(float(res_b.change[0]))


def test_nan_error_names_batch_index_when_only_a_subset_runs(params):
    u, v = sech_fields(3, params, dtype=torch.complex64)
    u[2, 5] = complex(float("nan"), 0.0)
    angles = torch.deg2rad(torch.tensor([MODELOCK_DEG] * 3))
    with pytest.raises(NonFiniteFieldError, match=r"cavity 2\b") as info:
        run_to_convergence(u, v, angles, 0.1, params, tol=1e-5, max_round_trips=2,
                           active=torch.tensor([False, True, True]))
    assert info.value.cavities == [2]
