"""Hostile inputs to the physics functions: one clear error naming the input (and the
cavity), never a NaN that comes back silently."""
import pytest
import torch

from laserrl.physics import CavityParams, NonFiniteFieldError, propagate, reward_terms, round_trip, run_to_convergence, sech_fields
from laserrl.physics.checks import MAX_PEAK_POWER

P = CavityParams(n=64)
NAN, INF = float("nan"), float("inf")


def _fields():
    return sech_fields(3, P)


def _with(x, row, value):
    x = x.clone()
    x[row, 5] = value
    return x


ANGLES = torch.zeros(3, 4)


@pytest.mark.parametrize("fn", [round_trip, run_to_convergence])
@pytest.mark.parametrize("bad, pattern", [
    (torch.tensor([[0.0] * 4, [0.0] * 4, [NAN, 0, 0, 0]]), r"angles of cavity 2 must be finite"),
    (torch.tensor([[0.0] * 4, [0, INF, 0, 0], [0.0] * 4]), r"angles of cavity 1 must be finite"),
])
def test_non_finite_angles_are_named(fn, bad, pattern):
    u, v = _fields()
    with pytest.raises(ValueError, match=pattern):
        fn(u, v, bad, 0.1, P)


@pytest.mark.parametrize("fn", [round_trip, propagate, run_to_convergence])
@pytest.mark.parametrize("K, pattern", [
    (INF, r"^K must be finite"),
    (torch.tensor([0.1, NAN, 0.1]), r"K of cavity 1 must be finite"),
])
def test_non_finite_K_is_named(fn, K, pattern):
    u, v = _fields()
    args = (u, v, K, P) if fn is propagate else (u, v, ANGLES, K, P)
    with pytest.raises(ValueError, match=pattern):
        fn(*args)


@pytest.mark.parametrize("fn", [round_trip, propagate, reward_terms, run_to_convergence])
@pytest.mark.parametrize("value", [complex(NAN, 0.0), complex(0.0, INF)])
def test_non_finite_fields_name_the_cavity(fn, value):
    u, v = _fields()
    v = _with(v, 1, value)
    args = {round_trip: (u, v, ANGLES, 0.1, P), propagate: (u, v, 0.1, P), reward_terms: (u, v, P),
            run_to_convergence: (u, v, ANGLES, 0.1, P)}[fn]
    with pytest.raises(NonFiniteFieldError, match=r"cavity 1\b") as info:
        fn(*args)
    assert info.value.cavities == [1]


@pytest.mark.parametrize("fn", [round_trip, propagate, run_to_convergence])
def test_huge_fields_are_refused(fn):
    u, v = _fields()
    u = _with(u, 2, complex(2 * MAX_PEAK_POWER ** 0.5, 0.0))
    args = (u, v, 0.1, P) if fn is propagate else (u, v, ANGLES, 0.1, P)
    with pytest.raises(ValueError, match=r"field of cavity 2 has peak power .* > MAX_PEAK_POWER"):
        fn(*args)


def test_large_but_physical_fields_still_run():
    u, v = _fields()
    u1, v1 = round_trip(u * 3.0, v * 3.0, ANGLES, 0.1, P)  # 9x the paper's initial power
    assert torch.isfinite(torch.view_as_real(u1)).all() and torch.isfinite(torch.view_as_real(v1)).all()
