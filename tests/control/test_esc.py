"""ESC climbs: on a known smooth objective (one and two angles, batched), and on the cavity
from a near-lock start; its filters are scipy's, applied sample by sample."""
import numpy as np
import pytest
import torch
from scipy import signal

from laserrl.control import CavityPlant, ESCParams, ExtremumSeeking, StepFilter
from laserrl.control.app import run_controllers

from plants import BumpPlant, start_angles


def test_step_filter_matches_scipy_on_a_whole_sequence():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((3, 50))
    for kind, cutoff, order in [("high", 0.05, 1), ("low", 0.1, 2)]:
        f = StepFilter(kind, cutoff, order, (3,))
        y = np.stack([f(x[:, k]) for k in range(50)], axis=1)
        b, a = signal.butter(order, cutoff, btype=kind, fs=1.0)
        np.testing.assert_allclose(y, signal.lfilter(b, a, x, axis=-1), atol=1e-12)


def test_step_filter_reset_starts_in_steady_state():
    f = StepFilter("high", 0.05, 2, (4,))
    f.reset(np.full(4, 0.2))
    assert np.abs(f(np.full(4, 0.2))).max() < 1e-12  # a constant passes a high-pass as 0 from the first sample
    mask = np.array([True, False, True, False])
    f.state[:] = 5.0
    f.reset(np.zeros(4), mask)
    assert (f.state[mask] == 0).all() and (f.state[~mask] == 5.0).all()


def test_esc_climbs_a_smooth_objective_one_angle_batched():
    optimum = torch.tensor([[-20.0], [-30.0], [-25.0]])
    plant = BumpPlant(3, optimum)
    esc = ExtremumSeeking(ESCParams(amplitude_deg=1.0, gain=150.0), ["alpha1"], 3)
    start = start_angles([-32.0, -19.0, -25.0], 3)  # below, above, at the optimum
    trace = run_controllers({"esc": esc}, plant, np.zeros((3, 150)), start)["esc"]
    final = trace["angles"][:, -20:, 0].mean(1)
    np.testing.assert_allclose(final, optimum[:, 0].numpy(), atol=1.0)
    assert (trace["r"][:, -20:].mean(1) > 0.199).all()


def test_esc_two_angles_each_with_its_own_frequency():
    plant = BumpPlant(2, [[-20.0, 10.0]], controlled_idx=(0, 1))
    params = ESCParams(amplitude_deg=1.0, gain=150.0, frequency={"alpha1": 0.125, "alpha2": 0.1})
    esc = ExtremumSeeking(params, ["alpha1", "alpha2"], 2)
    start = start_angles([-28.0, -14.0], 2)
    start[:, 1] = [4.0, 16.0]
    trace = run_controllers({"esc": esc}, plant, np.zeros((2, 300)), start)["esc"]
    final = trace["angles"][:, -24:, :2].mean(1)
    np.testing.assert_allclose(final, [[-20.0, 10.0]] * 2, atol=1.0)
    # the dither on alpha2 has its own period: 10 steps
    d = trace["angles"][0, -40:, 1] - trace["angles"][0, -40:, 1].mean()
    assert np.corrcoef(d[:-10], d[10:])[0, 1] > 0.9 and np.corrcoef(d[:-5], d[5:])[0, 1] < -0.5


def test_esc_tracks_a_drifting_optimum():
    plant = BumpPlant(1, [[-20.0]], K_shift_deg=-50.0)  # the optimum moves by -50 deg per unit K
    esc = ExtremumSeeking(ESCParams(amplitude_deg=1.0, gain=150.0), ["alpha1"], 1)
    K = np.linspace(0.1, 0.2, 200)[None]  # optimum -25 -> -30 deg
    trace = run_controllers({"esc": esc}, plant, K, start_angles([-25.0], 1))["esc"]
    assert abs(trace["angles"][0, -16:, 0].mean() - (-30.0)) < 1.0


@pytest.mark.parametrize("bad, match", [
    ({"frequency": {"alpha1": 0.1, "alpha2": 0.1}}, "differ"), ({"frequency": 0.6}, r"\(0, 0.5\)"),
    ({"amplitude_deg": 0.0}, "amplitude_deg"), ({"gain": -1.0}, "gain"), ({"highpass_cutoff": 0.5}, "highpass_cutoff"),
    ({"filter_order": 0}, "filter_order"), ({"amplitude_deg": {"alpha9": 1.0}}, "alpha9"),
])
def test_bad_esc_settings_name_the_setting(bad, match):
    with pytest.raises(ValueError, match=match):
        ExtremumSeeking(ESCParams(**bad), ["alpha1", "alpha2"], 1)


def test_esc_improves_r_on_the_cavity_from_a_near_lock_start():
    """K = 0.1, alpha1 = -34 deg: mode-locked at r ~ 0.17; r rises towards alpha1 ~ -24 deg.
    The paper's grid; 15 round trips per step keep the test short."""
    env_cfg = {"max_round_trips": 15, "tol": None, "dtype": "complex64", "compile": False,
               "physics": {"n": 256, "z_steps": 4}}
    plant = CavityPlant(env_cfg, ["alpha1"], 1, steps=30)
    esc = ExtremumSeeking(ESCParams(amplitude_deg=1.0, gain=150.0), ["alpha1"], 1)
    trace = run_controllers({"esc": esc}, plant, np.full((1, 30), 0.1), start_angles([-34.0], 1))["esc"]
    r = trace["r"][0]
    assert r[:3].mean() < 0.185, r
    assert r[-6:].mean() > r[:3].mean() + 0.01, r
    assert trace["angles"][0, -1, 0] > trace["angles"][0, 0, 0] + 3  # it moved towards the optimum
