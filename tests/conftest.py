"""Shared fixtures: the DOP853 reference solutions and small field helpers."""
from __future__ import annotations

import ast
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from laserrl.paths import REFERENCE_DATA
from laserrl.physics import CavityParams

DATA = REFERENCE_DATA
# The suite runs small batches (a few cavities of 256 samples): intra-op threading only
# adds synchronisation cost there, and on a loaded 2-core machine a multi-threaded FFT
# of a tiny array can take milliseconds instead of microseconds.
torch.set_num_threads(1)

CASES = ("siso_modelock", "siso_planewave", "miso_start", "k_neg", "noise_start")


@dataclass(frozen=True)
class RefCase:
    """One stored reference trajectory (see /work/shared/reference/README.md)."""

    name: str
    u0: np.ndarray
    v0: np.ndarray
    angles_deg: np.ndarray  # (4,) alpha1, alpha2, alpha3, alpha_p
    K: float
    u: np.ndarray  # (rounds, n) after each round trip
    v: np.ndarray
    change: np.ndarray
    E: float
    M4: float
    r: float

    @property
    def angles_rad(self) -> np.ndarray:
        return np.deg2rad(self.angles_deg)

    @property
    def rounds(self) -> int:
        return self.u.shape[0]


@pytest.fixture(scope="session")
def ref_npz():
    with np.load(DATA) as d:
        return {k: d[k] for k in d.files}


@pytest.fixture(scope="session")
def ref_params(ref_npz) -> dict:
    """The `params` entry of the npz: a string repr of a dict."""
    return ast.literal_eval(str(ref_npz["params"]))


@pytest.fixture(scope="session")
def ref_cases(ref_npz) -> dict[str, RefCase]:
    def case(name):
        g = lambda key: ref_npz[f"{name}/{key}"]  # noqa: E731
        return RefCase(
            name=name, u0=g("u0"), v0=g("v0"), angles_deg=g("angles_deg").astype(float), K=float(g("K")),
            u=g("u"), v=g("v"), change=g("change"), E=float(g("E")), M4=float(g("M4")), r=float(g("r")),
        )

    return {name: case(name) for name in CASES}


@pytest.fixture(params=CASES)
def ref_case(request, ref_cases) -> RefCase:
    return ref_cases[request.param]


@pytest.fixture(scope="session")
def params() -> CavityParams:
    return CavityParams()


def _to_numpy(x):
    return x.detach().cpu().numpy().astype(np.complex128) if torch.is_tensor(x) else np.asarray(x, np.complex128)


def rel_l2(u, v, u_ref, v_ref) -> np.ndarray:
    """Relative L2 error over both fields, per cavity (last axis is time)."""
    u, v, u_ref, v_ref = (_to_numpy(x) for x in (u, v, u_ref, v_ref))
    num = np.abs(u - u_ref) ** 2 + np.abs(v - v_ref) ** 2
    den = np.abs(u_ref) ** 2 + np.abs(v_ref) ** 2
    return np.sqrt(num.sum(-1) / den.sum(-1))


@pytest.fixture(scope="session")
def rel_err():
    """rel_l2(u, v, u_ref, v_ref) -> per-cavity relative L2 error over both fields."""
    return rel_l2


@pytest.fixture(scope="session")
def sech_np(params):
    """0.5 sech(t/2) on the default grid, numpy float64, computed independently of the package."""
    t = np.linspace(-params.T / 2, params.T / 2, params.n + 1)[: params.n]
    return 0.5 / np.cosh(t / 2.0)

