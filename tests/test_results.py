"""laserrl.results: failure modes of an evaluation, counted from its per-start paths."""
import pytest

from laserrl.results import failure_line, failure_modes


def _start(K, rewards, angles, success):
    """One per_start entry as evaluate_policy writes it (steps_to_lock: 1 + the first step with r >= 0.15)."""
    first = next((t for t, x in enumerate(rewards) if x >= 0.15), None)
    return {"K": K, "reward_path": rewards, "angle_path_deg": angles, "success": success,
            "steps_to_lock": None if first is None else first + 1}


def _result(per_start, hold_r=0.1):
    return {"success_r": 0.15, "hold_r": hold_r, "per_start": per_start}


STILL = [[0.0, 0.0]] * 6
MOVING = [[float(t), 0.0] for t in range(6)]


def test_failures_split_into_never_locked_and_lost_with_steps_locked():
    per_start = [
        _start(0.1, [0.05, 0.16, 0.16, 0.16, 0.16, 0.16], STILL, True),      # locked at 1, held: success
        _start(0.1, [0.05, 0.05, 0.05, 0.05, 0.05, 0.05], MOVING, False),    # never locked
        _start(0.2, [0.16, 0.12, 0.11, 0.09, 0.16, 0.16], MOVING, False),    # locked at 0, lost at 3
        _start(0.2, [0.02, 0.02, 0.15, 0.14, 0.13, 0.05], MOVING, False),    # locked at 2, lost at 5
    ]
    f = failure_modes(_result(per_start))
    assert (f["failed"], f["never_locked"], f["lost"]) == (3, 1, 2)
    assert f["steps_locked_before_loss"] == {"median": 3, "min": 3, "max": 3}
    assert f["by_K"] == {"0.1": {"never_locked": 1, "lost": 0}, "0.2": {"never_locked": 0, "lost": 2}}
    # after a lock: 4 still steps (the success) against 5 + 3 moving ones (the two lost)
    assert f["hold_action_after_lock"] == pytest.approx(4 / 12)
    line = failure_line(f)
    assert "never locked 1" in line and "lost it 2" in line and "33.3 %" in line


def test_without_a_hold_level_a_lost_lock_has_no_length():
    per_start = [_start(0.0, [0.2, 0.2, 0.05], MOVING[:3], False)]
    f = failure_modes(_result(per_start, hold_r=None))
    assert (f["lost"], f["steps_locked_before_loss"]) == (1, None)


def test_no_lock_anywhere_gives_no_hold_fraction():
    f = failure_modes(_result([_start(0.0, [0.01] * 3, MOVING[:3], False)]))
    assert f["hold_action_after_lock"] is None and f["never_locked"] == 1
    assert "all-hold" not in failure_line(f)


def test_with_held_steps_a_late_lock_held_to_the_end_is_counted_apart_from_a_lost_one():
    per_start = [
        _start(0.1, [0.05, 0.16, 0.16, 0.16, 0.16, 0.16], STILL, True),      # early lock, held: success
        _start(0.1, [0.05, 0.05, 0.05, 0.05, 0.16, 0.16], MOVING, False),    # locks at 4: held 2 < 3 steps
        _start(0.2, [0.16, 0.12, 0.11, 0.09, 0.16, 0.16], MOVING, False),    # locked at 0, lost at 3
    ]
    f = failure_modes({**_result(per_start), "held_steps": 3})
    assert (f["failed"], f["never_locked"], f["lost"], f["locked_late"]) == (2, 0, 1, 1)
    assert f["steps_locked_before_loss"] == {"median": 3, "min": 3, "max": 3}
    assert f["by_K"]["0.1"] == {"never_locked": 0, "lost": 0, "locked_late": 1}
    assert "locked too late 1" in failure_line(f)
    assert "locked_late" not in failure_modes(_result(per_start)) and "too late" not in failure_line(failure_modes(_result(per_start)))
