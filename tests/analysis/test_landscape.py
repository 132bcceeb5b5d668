"""Landscapes swept with the state carried over: hysteresis where the cavity is bistable,
agreement where its state is unique, and a difference from cold starts."""
import pytest
import torch

from laserrl.analysis import StepSettings, cold_landscape, interval_width, intervals, sweep
from laserrl.envs import LaserTask
from laserrl.physics import CavityParams

# A coarser grid than the defaults (n = 128, 4 Strang steps) keeps the sweeps to seconds and
# keeps the paper's bistability: at alpha2, alpha3, alpha_p = 3, 28, 88 deg and K = 0.1 a pulse
# survives turning alpha1 up from -36 deg to about -20 deg, while turning it down from -16 deg
# stays on the plane wave until about -32 deg.
PARAMS = CavityParams(n=128, z_steps=4)
SETTINGS = StepSettings(max_round_trips=30, tol=1e-5, settle_round_trips=100)
BASE = [0.0, 3.0, 28.0, 88.0]
GRID = [-36.0, -32.0, -28.0, -24.0, -20.0, -16.0]


@pytest.fixture(scope="module")
def alpha1_sweep():
    return sweep("alpha1", GRID, BASE, 0.1, PARAMS, SETTINGS)


@pytest.fixture(scope="module")
def cold():
    return cold_landscape("alpha1", GRID, BASE, 0.1, PARAMS, SETTINGS)[0]


def test_sweeps_find_the_hysteresis_where_the_cavity_is_bistable(alpha1_sweep):
    sw = alpha1_sweep
    found = sw.hysteresis(0.05)
    assert len(found) == 1
    lo, hi = found[0]
    assert GRID[0] < lo <= hi < GRID[-1]
    inside = (sw.values_deg >= lo) & (sw.values_deg <= hi)
    # the two branches: a pulse reached from below, a plane wave (r an order of magnitude lower) from above
    assert bool((sw.r_up[0][inside] > 5 * sw.r_down[0][inside]).all())
    assert interval_width(found[0], sw.step_deg) == hi - lo + 4.0


def test_sweeps_agree_at_the_ends_where_the_state_is_unique(alpha1_sweep):
    sw = alpha1_sweep
    for j in (0, -1):
        assert abs(float(sw.r_up[0, j] - sw.r_down[0, j])) < 0.05 * float(sw.r_up[0, j]) + 1e-3


def test_sweeping_carries_the_state_a_cold_start_does_not(alpha1_sweep, cold):
    sw = alpha1_sweep
    # each sweep starts with a cold start at its first angle ...
    assert torch.allclose(sw.r_up[0, 0], cold[0], rtol=1e-4)
    assert torch.allclose(sw.r_down[0, -1], cold[-1], rtol=1e-4)
    # ... and then remembers where it came from: the pulse carried up differs from a fresh start
    assert bool(((sw.r_up[0] - cold).abs() > 0.05).any())


def test_intervals_are_the_runs_of_the_mask():
    assert intervals([0, 1, 2, 3, 4, 5], [True, True, False, True, False, True]) == [(0, 1), (3, 3), (5, 5)]
    assert intervals([0, 1], [False, False]) == []
    with pytest.raises(ValueError, match="differ in length"):
        intervals([0, 1], [True])


def test_settings_from_the_env_task_and_bad_input():
    s = StepSettings.from_task(LaserTask(max_round_trips=30, min_round_trips=3))
    assert (s.max_round_trips, s.min_round_trips, s.tol, s.dtype) == (30, 3, 1e-5, torch.complex64)
    with pytest.raises(ValueError, match="min_round_trips"):
        StepSettings(max_round_trips=1, min_round_trips=2)
    with pytest.raises(ValueError, match="max_round_trips"):
        StepSettings(max_round_trips=float("inf"))
    with pytest.raises(ValueError, match="strictly increasing"):
        sweep("alpha1", [0.0, 0.0], BASE, 0.1, PARAMS, SETTINGS)
    with pytest.raises(ValueError, match="angle must be one of"):
        sweep("alpha9", GRID, BASE, 0.1, PARAMS, SETTINGS)
    with pytest.raises(ValueError, match="base_deg"):
        sweep("alpha1", GRID, [0.0, 3.0], 0.1, PARAMS, SETTINGS)
