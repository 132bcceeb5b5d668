"""Cavities of one batch with their own D, E0, tau, g0, Gamma (``cavity``, laserrl.physics.checks):
the batch agrees with each cavity run alone with its own CavityParams, compiled or not; nominal
values reproduce the shared-parameter path; bad values name the parameter and the cavity."""
import pytest
import torch

from laserrl.physics import CavityParams
from laserrl.physics.cavity import propagate, round_trip
from laserrl.physics.checks import CAVITY_KEYS, check_cavity
from laserrl.physics.fields import sech_fields
from laserrl.physics.run import run_to_convergence

P = CavityParams(n=64)
ANGLES = torch.deg2rad(torch.tensor([[15.0, -5.0, 20.0, 84.0]] * 3, dtype=torch.float64))
K = torch.tensor([0.1, -0.1, 0.3], dtype=torch.float64)
# the nominal cavity and two within +-10 %
VALUES = torch.tensor([[P.D, P.E0, P.tau, P.g0, P.Gamma],
                       [-0.44, 4.0, 0.11, 1.6, 0.09],
                       [-0.37, 4.6, 0.092, 1.85, 0.11]], dtype=torch.float64)


def _own(i):
    return P.replace(**{k: float(VALUES[i, j]) for j, k in enumerate(CAVITY_KEYS)})


# complex64 compiled against complex64 eager: float32 rounding over four round trips of intense pulses
@pytest.mark.parametrize("dtype, compile, tol", [(torch.complex128, False, 1e-10), (torch.complex64, True, 1e-3)])
def test_a_batch_of_different_cavities_agrees_with_each_cavity_alone(dtype, compile, tol):
    u, v = sech_fields(3, P, 1.0, 1.0, dtype=dtype)
    out = run_to_convergence(u, v, ANGLES, K, P, tol=1e-5, max_round_trips=4, min_round_trips=4, compile=compile,
                             cavity=VALUES)
    alone = []
    for i in range(3):
        ref = run_to_convergence(u[i:i + 1], v[i:i + 1], ANGLES[i:i + 1], K[i:i + 1], _own(i), tol=1e-5,
                                 max_round_trips=4, min_round_trips=4)
        alone.append(ref.u[0])
        err = torch.linalg.vector_norm(out.u[i] - ref.u[0]) / torch.linalg.vector_norm(ref.u[0])
        assert float(err) < tol, (i, float(err))
    # the cavities really differ: a cavity 10 % off gives fields far beyond that tolerance
    for i in (1, 2):
        assert float(torch.linalg.vector_norm(alone[i] - alone[0]) / torch.linalg.vector_norm(alone[0])) > 30 * tol


def test_nominal_values_per_cavity_are_the_shared_parameters():
    u, v = sech_fields(3, P, 1.0, 1.0, dtype=torch.complex128)
    nominal = VALUES[:1].expand(3, 5)
    a = round_trip(u, v, ANGLES, K, P, cavity=nominal)
    b = round_trip(u, v, ANGLES, K, P)
    for x, y in zip(a, b):
        assert torch.allclose(x, y, rtol=0, atol=1e-13)


@pytest.mark.parametrize("column, value, message", [
    ("E0", 0.0, r"cavity.E0 must be finite and > 0, got \[0.0\] for cavity 1"),
    ("g0", float("nan"), r"cavity.g0 must be finite and >= 0, got \[nan\] for cavity 1"),
    ("Gamma", -0.1, r"cavity.Gamma must be finite and >= 0"),
    ("D", float("inf"), r"cavity.D must be finite"),
])
def test_bad_per_cavity_values_name_the_parameter_and_cavity(column, value, message):
    bad = VALUES.clone()
    bad[1, CAVITY_KEYS.index(column)] = value
    with pytest.raises(ValueError, match=message):
        check_cavity(bad, 3, P)


def test_per_cavity_values_need_the_split_step_and_the_batch_shape():
    u, v = sech_fields(3, P, 1.0, 1.0, dtype=torch.complex128)
    with pytest.raises(ValueError, match=r"shape \(3, 5\)"):
        propagate(u, v, K, P, cavity=VALUES[:2])
    with pytest.raises(ValueError, match="integrator='split'"):
        propagate(u, v, K, CavityParams.precise(n=64), cavity=VALUES)


def test_compiled_calls_with_and_without_per_cavity_values_alternate():
    """One compiled stepper serves per-cavity batches (training with env.physics_spread) and nominal
    ones (its validation) in any order and batch size; the nominal results do not depend on it."""
    from laserrl.envs.step import draw_cavities

    nominal = {}
    for B, spread in [(4, True), (4, False), (3, True), (2, False), (4, True), (2, False)]:
        u, v = sech_fields(B, P, 1.0, 1.0, dtype=torch.complex64)
        K = torch.full((B,), 0.1, dtype=torch.float64)
        cavity = draw_cavities(P, (0.1,) * 5, B, torch.Generator().manual_seed(B)) if spread else None
        out, _ = propagate(u, v, K, P, compile=True, cavity=cavity)
        assert bool(torch.isfinite(torch.view_as_real(out)).all())
        if not spread:
            nominal.setdefault(B, out)
            assert torch.equal(out, nominal[B])
