"""Metrics of a controlled run, per cavity and averaged over cavities.

With r(t) the reward after agent step t (t = 0 .. T-1) and "locked" meaning r >= locked_r:

* ``frac_locked``: fraction of the T steps that are locked;
* ``mean_r``: mean of r over the T steps;
* ``first_lock_step``: steps until the first lock, t + 1 for the first t that starts a run of
  ``hold_steps`` consecutive locked steps (None if there is none);
* ``locked_after_first_lock``: fraction of the steps from the first lock to the end that are
  locked (None if there is no lock): how well a controller holds what it found;
* ``recovery_steps``: for every jump of K at step t_j, s - t_j for the first s >= t_j that
  starts a run of ``hold_steps`` locked steps before the next jump (or the end); 0 when the
  lock survives the jump, None when the cavity does not lock again in time;
* ``round_trips``: cavity round trips spent over the run;
* ``held_to_end`` (with ``success_r`` given): r reaches ``success_r`` and stays >= locked_r at
  every later step to the end: ``laserrl-eval``'s success with ``hold_r`` = locked_r;
* ``after_first_lock_by_K`` (where K moves within a run): the steps from each cavity's first
  lock pooled over the cavities and sorted into bands of K (``locked_by_K``): where the time
  unlocked is lost.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np


def lock_starts(locked: np.ndarray, hold_steps: int) -> np.ndarray:
    """(B, T) bool: step t starts a run of ``hold_steps`` locked steps (within the array)."""
    B, T = locked.shape
    if T < hold_steps:
        return np.zeros_like(locked)
    windows = np.lib.stride_tricks.sliding_window_view(locked, hold_steps, axis=1).all(-1)  # (B, T - hold + 1)
    return np.concatenate([windows, np.zeros((B, hold_steps - 1), dtype=bool)], axis=1)


def _first(mask: np.ndarray) -> list[int | None]:
    return [int(np.argmax(row)) if row.any() else None for row in mask]


def held_to_end(r: np.ndarray, success_r: float, locked_r: float) -> np.ndarray:
    """(B,) bool: some step reaches r >= success_r and no later step falls below locked_r."""
    import torch

    from laserrl.evaluate import success_mask

    return success_mask(torch.from_numpy(np.asarray(r, dtype=np.float64)), success_r, locked_r).numpy()


def per_cavity(r: np.ndarray, round_trips: np.ndarray, jump_times: Sequence[int], locked_r: float,
               hold_steps: int, success_r: float | None = None) -> dict:
    """Metrics of every cavity from r (B, T) and round trips (B, T)."""
    B, T = r.shape
    locked = r >= locked_r
    first = _first(lock_starts(locked, hold_steps))
    bounds = list(jump_times) + [T]
    recovery = []
    for j, t0 in enumerate(jump_times):
        starts = lock_starts(locked[:, t0: bounds[j + 1]], hold_steps)
        recovery.append(_first(starts))  # relative to the jump already
    return {
        "frac_locked": locked.mean(1).tolist(),
        "mean_r": r.mean(1).tolist(),
        "first_lock_step": [None if f is None else f + 1 for f in first],
        "locked_after_first_lock": [None if f is None else float(locked[b, f:].mean()) for b, f in enumerate(first)],
        "recovery_steps": [[recovery[j][b] for j in range(len(jump_times))] for b in range(B)],
        "round_trips": round_trips.sum(1).astype(int).tolist(),
        **({} if success_r is None else {"held_to_end": held_to_end(r, success_r, locked_r).tolist()}),
    }


def locked_by_K(r: np.ndarray, K: np.ndarray, first_lock_step: Sequence[int | None], locked_r: float,
                width: float = 0.1) -> list[dict]:
    """The steps from each cavity's first lock (``first_lock_step``, 1-based as ``per_cavity``'s) to
    the end, pooled over cavities and sorted by the K they ran at into bands [k w, (k + 1) w):
    per band ``K`` (its edges), ``steps``, ``locked`` (their fraction with r >= locked_r) and
    ``share_of_unlocked`` (the band's part of all unlocked steps). Bands without steps are left out."""
    if not width > 0:
        raise ValueError(f"width must be > 0, got {width!r}")
    after = np.zeros(r.shape, dtype=bool)
    for b, f in enumerate(first_lock_step):
        if f is not None:
            after[b, f - 1:] = True
    band = np.floor(np.asarray(K, dtype=np.float64) / width + 1e-9).astype(np.int64)
    unlocked = after & (r < locked_r)
    total_unlocked = max(int(unlocked.sum()), 1)
    out = []
    for k in np.unique(band[after]):
        steps = after & (band == k)
        out.append({"K": [round(float(k * width), 10), round(float((k + 1) * width), 10)], "steps": int(steps.sum()),
                    "locked": float(1 - unlocked[steps].mean()), "share_of_unlocked": float(unlocked[steps].sum() / total_unlocked)})
    return out


def spread(values: Sequence[float | None]) -> dict:
    """Mean, standard deviation, min and max over cavities of the defined values; ``n`` of them."""
    x = np.array([v for v in values if v is not None], dtype=np.float64)
    if x.size == 0:
        return {"mean": None, "std": None, "min": None, "max": None, "n": 0}
    return {"mean": float(x.mean()), "std": float(x.std()), "min": float(x.min()), "max": float(x.max()),
            "n": int(x.size)}


def summarise(cav: dict, num_jumps: int) -> dict:
    """Average over cavities (with spread) of ``per_cavity``'s metrics."""
    B = len(cav["mean_r"])
    out = {k: spread(cav[k]) for k in ("frac_locked", "mean_r", "first_lock_step", "locked_after_first_lock",
                                       "round_trips")}
    out["locked_ever"] = sum(v is not None for v in cav["first_lock_step"]) / B
    if "held_to_end" in cav:
        out["held_to_end"] = sum(cav["held_to_end"]) / B
    pooled = [rec[j] for rec in cav["recovery_steps"] for j in range(num_jumps)]
    out["recovery_steps"] = spread(pooled)
    out["recovered"] = (sum(v is not None for v in pooled) / len(pooled)) if pooled else None
    out["recovery_by_jump"] = [spread([rec[j] for rec in cav["recovery_steps"]]) for j in range(num_jumps)]
    return out


def held_by_K0(cav: dict, K0: Sequence[float]) -> dict[str, float]:
    """Fraction of the cavities of each start value ``K0[i % len(K0)]`` that held to the end."""
    groups: dict[str, list[bool]] = {}
    for i, ok in enumerate(cav["held_to_end"]):
        groups.setdefault(f"{K0[i % len(K0)]:g}", []).append(bool(ok))
    return {k: sum(v) / len(v) for k, v in groups.items()}
