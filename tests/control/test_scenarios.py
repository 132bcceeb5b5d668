"""K scenarios produce what they are configured to: jumps at the configured times, bounded
drift with the configured step size, the sinusoid's amplitude and period, one trajectory
per cavity that does not depend on the batch."""
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from laserrl.control import Scenario
from laserrl.paths import CONF_DIR

CONF = Path(CONF_DIR)
SCENARIOS = sorted(p.stem for p in (CONF / "scenario").glob("*.yaml"))


def _scenario(name, overrides=()):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="control", overrides=[f"scenario={name}", *overrides])
    return Scenario(**OmegaConf.to_container(cfg.scenario, resolve=True))


def test_all_six_scenarios_exist():
    assert set(SCENARIOS) == {"constant", "random_walk", "sinusoid", "jumps", "drift_jumps", "drift_jumps_wide"}


@pytest.mark.parametrize("name", SCENARIOS)
def test_every_scenario_stays_within_bounds_and_starts_in_its_box(name):
    sc = _scenario(name)
    K, angles = sc.sample(16, seed=3)
    assert K.shape == (16, sc.steps) and angles.shape == (16, 4)
    assert (K >= sc.bounds[0]).all() and (K <= sc.bounds[1]).all()
    lo, hi = sc.init_angles_deg["alpha1"]
    assert (angles[:, 0] >= lo).all() and (angles[:, 0] <= hi).all()
    assert len(set(angles[:, 0])) == (16 if lo < hi else 1)  # a range draws one start per cavity


def test_the_wide_scenario_starts_at_the_four_controller_start_and_jumps_across_the_whole_range():
    sc = _scenario("drift_jumps_wide")
    K, angles = sc.sample(64, seed=0)
    assert np.allclose(angles, [15.0, -5.0, 20.0, 84.0]) and sc.init_fields == "noise"
    assert K.min() < -0.1 and K.max() > 0.3  # drift and jumps reach both ends of [-0.2, 0.4]
    jumps = np.abs(K[:, 100] - K[:, 99])
    assert (jumps >= 0.2).all()


def test_constant():
    K, _ = _scenario("constant").sample(4, seed=0)
    assert (K == 0.1).all()


def test_a_list_of_K0_gives_each_cavity_its_value_in_turn():
    sc = _scenario("constant", ["scenario.K0=[0.0,0.2,0.4]", "scenario.bounds=[-0.2,0.4]"])
    K, _ = sc.sample(7, seed=0)
    assert np.array_equal(K[:, 0], [0.0, 0.2, 0.4, 0.0, 0.2, 0.4, 0.0]) and (K == K[:, :1]).all()
    drifting = _scenario("drift_jumps_wide", ["scenario.K0=[-0.2,0.4]"]).sample(2, seed=0)[0]
    assert drifting[0, 0] == -0.2 and drifting[1, 0] == 0.4 and not (drifting[0] == -0.2).all()


def test_jumps_at_the_configured_times_and_only_there():
    sc = _scenario("jumps", ["scenario.jumps.times=[40,90]", "scenario.jumps.min_size=0.15"])
    K, _ = sc.sample(32, seed=1)
    changes = np.abs(np.diff(K, axis=1)) > 0
    assert set(np.nonzero(changes.any(0))[0] + 1) == {40, 90}
    assert (np.abs(K[:, 40] - K[:, 39]) >= 0.15).all() and (np.abs(K[:, 90] - K[:, 89]) >= 0.15).all()
    assert (K[:, :40] == 0.1).all()
    # the targets spread over the jump range
    assert K[:, 90].min() < 0.1 and K[:, 40].max() > 0.3


def test_random_walk_steps_have_the_configured_size_and_stay_bounded():
    sc = _scenario("random_walk", ["scenario.drift.sigma=0.004", "scenario.steps=400"])
    K, _ = sc.sample(32, seed=2)
    steps = np.diff(K, axis=1)
    inside = (K[:, :-1] > 0.02) & (K[:, :-1] < 0.38)  # away from the reflecting walls
    assert abs(steps[inside].std() - 0.004) < 0.0004 and abs(steps[inside].mean()) < 0.0004
    wide = _scenario("random_walk", ["scenario.drift.sigma=0.05"]).sample(8, seed=0)[0]
    assert wide.min() >= 0.0 and wide.max() <= 0.4 and wide.min() < 0.02 and wide.max() > 0.38  # reflected, not escaped


def test_sinusoid_amplitude_and_period():
    sc = _scenario("sinusoid", ["scenario.drift.amplitude=0.1", "scenario.drift.period=50", "scenario.K0=0.2"])
    K, _ = sc.sample(8, seed=0)
    assert np.allclose(K.max(1) - K.min(1), 0.2, atol=0.01)
    assert np.allclose(K[:, 50:], K[:, :-50], atol=1e-12)  # period 50 steps
    assert len(set(np.round(K[:, 0], 6))) == 8  # own phase per cavity


def test_drift_plus_jumps_drifts_between_jumps():
    sc = _scenario("drift_jumps")
    K, _ = sc.sample(16, seed=0)
    t1, t2 = sc.jumps["times"]
    assert (np.abs(np.diff(K[:, 1:t1], axis=1)) > 0).mean() > 0.9  # drifting
    assert (np.abs(K[:, t1] - K[:, t1 - 1]) >= sc.jumps["min_size"]).all()


def test_a_cavity_has_its_trajectory_whatever_the_batch():
    sc = _scenario("drift_jumps")
    K2, a2 = sc.sample(2, seed=7)
    K5, a5 = sc.sample(5, seed=7)
    assert np.array_equal(K2, K5[:2]) and np.array_equal(a2, a5[:2])
    assert not np.array_equal(K5[0], K5[1]) and not np.array_equal(sc.sample(2, seed=8)[0], K2)


@pytest.mark.parametrize("override, match", [
    ("scenario.jumps.times=[0]", "jumps.times"), ("scenario.jumps.times=[500]", "jumps.times"),
    ("scenario.jumps.times=[50,20]", "jumps.times"), ("scenario.K0=0.9", "K0"), ("scenario.K0=[0.1,0.9]", "K0"),
    ("scenario.K0=[]", "K0"), ("scenario.K0=high", "K0"),
    ("scenario.bounds=[0.4,0.0]", "bounds"), ("scenario.drift.kind=brownian", "drift.kind"),
    ("scenario.drift.sigma=-1", "drift.sigma"), ("scenario.steps=0", "steps"),
    ("scenario.jumps.range=[-1,0.4]", "jumps.range"),
])
def test_bad_scenarios_name_the_value(override, match):
    with pytest.raises(ValueError, match=match):
        _scenario("drift_jumps", [override])
