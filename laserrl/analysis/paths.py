"""Angle paths replayed through the cavity physics, one agent step per point of the path.

The paper's fig. 4(b) compares the path the agent takes from alpha1 = -15, alpha2 = -3 deg
with the straight path between the same start and end: with the state carried along,
the agent's path ends on a mode-locked pulse (r = 0.2062) and the straight one on a plane
wave (r = 0.0066). ``straight_path`` builds the comparison path, ``follow_paths`` runs
any batch of paths (the agent's, replayed, and the straight one) with the env's
per-step numerics and returns r after each step and the final fields u, v.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import torch

from laserrl.analysis.landscape import StepSettings, initial_state
from laserrl.envs.step import step_cavity
from laserrl.envs.laser_env import ANGLE_NAMES
from laserrl.physics import CavityParams, sech_fields


def straight_path(start_deg, end_deg, steps: int) -> torch.Tensor:
    """``steps`` points from ``start_deg`` to ``end_deg`` on the straight line, (steps, m):
    point k (1..steps) is start + k / steps (end - start); the start itself is not included
    (it is the state before the first step), the end is the last point."""
    start = torch.as_tensor(start_deg, dtype=torch.float64).flatten()
    end = torch.as_tensor(end_deg, dtype=torch.float64).flatten()
    if start.shape != end.shape:
        raise ValueError(f"start_deg {start.tolist()} and end_deg {end.tolist()} need the same number of angles")
    if isinstance(steps, bool) or int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    frac = torch.arange(1, int(steps) + 1, dtype=torch.float64)[:, None] / int(steps)
    return start + frac * (end - start)


def full_angles(path_deg, controlled: Sequence[str], base_deg: Mapping[str, float] | Sequence[float]) -> torch.Tensor:
    """A path of the ``controlled`` angles (..., T, m) completed with the fixed angles of
    ``base_deg`` (a mapping by name or the four angles), (..., T, 4) deg."""
    path = torch.as_tensor(path_deg, dtype=torch.float64)
    if isinstance(base_deg, Mapping):
        base_deg = [float(base_deg[name]) for name in ANGLE_NAMES]
    base = torch.as_tensor(base_deg, dtype=torch.float64)
    if path.shape[-1] != len(controlled):
        raise ValueError(f"path has {path.shape[-1]} angles per point, controlled names {len(controlled)}")
    out = base.expand(*path.shape[:-1], 4).clone()
    for k, name in enumerate(controlled):
        out[..., ANGLE_NAMES.index(name)] = path[..., k]
    return out


@dataclass
class PathResult:
    """Replayed paths: r after each step, the final fields and, if recorded, the fields after each step."""

    r: torch.Tensor  # (B, T)
    u: torch.Tensor  # (B, n) final
    v: torch.Tensor
    round_trips: torch.Tensor  # (B, T)
    u_path: torch.Tensor | None = None  # (B, T, n) after each step (record_fields=True)
    v_path: torch.Tensor | None = None


def follow_paths(paths_deg, K, params: CavityParams, settings: StepSettings, *, u0=None, v0=None,
                 record_fields: bool = False) -> PathResult:
    """Run B cavities along B angle paths (B, T, 4) deg, one agent step per point.

    Starts from ``u0, v0`` (B, n) or, if not given, the paper's sech fields (the env's
    reset state). Each point is one ``laserrl.envs.step.step_cavity``, the env's own step: with
    the env's numerics (``StepSettings.from_task``) this reproduces its rollouts of the same angles.
    """
    paths = torch.as_tensor(paths_deg, dtype=torch.float64)
    if paths.ndim != 3 or paths.shape[-1] != 4:
        raise ValueError(f"paths_deg must have shape (B, T, 4), got {tuple(paths.shape)}")
    if not bool(torch.isfinite(paths).all()):
        raise ValueError("paths_deg must be finite")
    B, T = paths.shape[:2]
    if u0 is None:
        u, v = sech_fields(B, params, dtype=settings.dtype)
    else:
        u, v = u0.to(settings.dtype), v0.to(settings.dtype)
    state = initial_state(u, v, torch.deg2rad(paths[:, 0]), K)
    rs, rts, us, vs = [], [], [], []
    for t in range(T):
        state, out = step_cavity(state, torch.deg2rad(paths[:, t]), params, settings.step)
        rs.append(out.r.double())
        rts.append(out.round_trips)
        if record_fields:
            us.append(state.u)
            vs.append(state.v)
    u, v = state.u, state.v
    return PathResult(torch.stack(rs, 1), u, v, torch.stack(rts, 1),
                      torch.stack(us, 1) if record_fields else None, torch.stack(vs, 1) if record_fields else None)
