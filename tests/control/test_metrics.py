"""Control metrics from known traces of r."""
import numpy as np
import pytest

import torch

from laserrl.control.metrics import held_by_K0, locked_by_K, per_cavity, summarise
from laserrl.evaluate import success_mask


def test_locked_after_first_lock_counts_from_the_first_held_lock():
    r = np.array([[0.0, 0.2, 0.0, 0.2, 0.2, 0.05, 0.2, 0.2],   # a one-step blip, then locked from step 3 (t = 3)
                  [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],    # never locked
                  [0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2]])   # locked throughout
    cav = per_cavity(r, np.ones_like(r), jump_times=[4], locked_r=0.1, hold_steps=2)
    assert cav["first_lock_step"] == [4, None, 1]
    assert cav["locked_after_first_lock"] == [pytest.approx(4 / 5), None, 1.0]
    assert cav["frac_locked"][0] == pytest.approx(5 / 8)  # the blip counts in the time locked, not here
    s = summarise(cav, num_jumps=1)
    assert s["locked_after_first_lock"]["n"] == 2 and s["locked_after_first_lock"]["mean"] == pytest.approx(0.9)


def test_locked_by_K_sorts_the_steps_after_the_first_lock_into_bands_of_K():
    r = np.array([[0.0, 0.2, 0.2, 0.05, 0.05, 0.2],    # first lock at step 2; unlocked twice, at K = 0.35
                  [0.2, 0.2, 0.2, 0.2, 0.05, 0.2],     # first lock at step 1; unlocked once, at K = -0.15
                  [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])     # never locked: none of its steps count
    K = np.array([[0.1, 0.1, 0.1, 0.35, 0.35, 0.35],
                  [-0.15, -0.15, 0.0, 0.0, -0.15, -0.15],
                  [0.35, 0.35, 0.35, 0.35, 0.35, 0.35]])
    cav = per_cavity(r, np.ones_like(r), jump_times=[3], locked_r=0.1, hold_steps=2)
    assert cav["first_lock_step"] == [2, 1, None]
    bands = {tuple(b["K"]): b for b in locked_by_K(r, K, cav["first_lock_step"], locked_r=0.1)}
    assert list(bands) == [(-0.2, -0.1), (0.0, 0.1), (0.1, 0.2), (0.3, 0.4)]
    assert [b["steps"] for b in bands.values()] == [4, 2, 2, 3]
    assert bands[(0.3, 0.4)]["locked"] == pytest.approx(1 / 3) and bands[(-0.2, -0.1)]["locked"] == pytest.approx(3 / 4)
    assert bands[(0.3, 0.4)]["share_of_unlocked"] == pytest.approx(2 / 3)
    assert sum(b["share_of_unlocked"] for b in bands.values()) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="width"):
        locked_by_K(r, K, cav["first_lock_step"], locked_r=0.1, width=0)


def test_held_to_end_is_laserrl_evals_success():
    r = np.array([[0.0, 0.16, 0.12, 0.11, 0.1],    # reached 0.15, never below 0.1 after: held
                  [0.16, 0.05, 0.12, 0.12, 0.12],   # lost, and never back to 0.15
                  [0.16, 0.05, 0.16, 0.12, 0.12],   # lost, then reached again and held
                  [0.12, 0.12, 0.14, 0.12, 0.12]])  # never reached 0.15
    cav = per_cavity(r, np.ones_like(r), jump_times=[], locked_r=0.1, hold_steps=1, success_r=0.15)
    assert cav["held_to_end"] == [True, False, True, False]
    rng = np.random.default_rng(0)
    noisy = rng.random((500, 12)) * 0.2
    expected = success_mask(torch.from_numpy(noisy), 0.15, 0.1).tolist()
    assert per_cavity(noisy, np.ones_like(noisy), [], 0.1, 1, success_r=0.15)["held_to_end"] == expected
    assert summarise(cav, num_jumps=0)["held_to_end"] == 0.5
    assert held_by_K0(cav, [0.0, 0.2]) == {"0": 1.0, "0.2": 0.0}   # cavities 0, 2 at K0 = 0; 1, 3 at 0.2
