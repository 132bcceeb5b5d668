"""Control metrics from known traces of r."""
import numpy as np
import pytest

from laserrl.control.metrics import per_cavity, summarise


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
