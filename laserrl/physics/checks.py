"""Checks of the fields and per-cavity parameters that the physics functions take.

Fields: u, v are (B, n) complex tensors of one dtype and device, finite, with peak
power max_t(|u|^2 + |v|^2) <= ``MAX_PEAK_POWER``. Per-cavity parameters: K is (B,)
and the angles (alpha1, alpha2, alpha3, alpha_p) of J1 JP J2 J3 are (B, 4), real and
finite, or one value broadcast to every cavity. A failure names the field or
parameter and the cavities (batch indices); NaN or infinite fields raise
``NonFiniteFieldError``, everything else ``ValueError``.
"""
from __future__ import annotations

import numpy as np
import torch

from laserrl.physics.params import CavityParams

__all__ = ["check_fields", "check_finite", "check_cavity", "as_batch", "NonFiniteFieldError", "MAX_PEAK_POWER",
           "CAVITY_KEYS"]

#: The columns of per-cavity parameters ``cavity`` (B, 5): cavities of one batch that differ
#: from ``CavityParams`` in these (the others, and the grid, are shared).
CAVITY_KEYS = ("D", "E0", "tau", "g0", "Gamma")


def _real_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.complex128 else torch.float32


def _cavities(rows: list[int]) -> str:
    """'cavity 3' or 'cavity [0, 3]' for error messages."""
    return f"cavity {rows if len(rows) > 1 else rows[0]}"


class NonFiniteFieldError(FloatingPointError):
    """A cavity's field became NaN or infinite; ``cavities`` lists the batch indices."""

    def __init__(self, cavities: list[int], where: str = ""):
        self.cavities = cavities
        super().__init__(f"field of {_cavities(cavities)} is NaN or infinite{where}")


def _finite_rows(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return torch.isfinite(torch.view_as_real(u)).all((-1, -2)) & torch.isfinite(torch.view_as_real(v)).all((-1, -2))


def check_finite(u: torch.Tensor, v: torch.Tensor, where: str = "", index: torch.Tensor | None = None) -> None:
    """Raise NonFiniteFieldError naming the cavities (batch indices, or ``index[i]``) with NaN/inf fields."""
    bad = ~_finite_rows(u, v)
    if bool(bad.any()):
        rows = bad.nonzero().flatten()
        raise NonFiniteFieldError((rows if index is None else index[rows]).tolist(), where)


#: Largest accepted peak power |u|^2 + |v|^2 of an input field. Physical states of this
#: cavity peak at order 1-10 (E0 = 4.23); fields beyond this overflow the Kerr phase and
#: the gain integral into NaN, so they are refused up front.
MAX_PEAK_POWER = 1e6


def check_fields(u, v, params: CavityParams) -> None:
    """Raise an error naming the field or cavity unless u, v are matching (B, n) complex
    tensors with finite values and a peak power of at most ``MAX_PEAK_POWER``.

    NaN or infinite values raise ``NonFiniteFieldError`` (with the cavities' batch indices);
    wrong types or shapes and huge fields raise ``ValueError``. Costs one host sync.
    """
    for name, x in (("u", u), ("v", v)):
        if not torch.is_tensor(x) or not x.is_complex():
            raise ValueError(f"field {name} must be a complex tensor, got {getattr(x, 'dtype', type(x).__name__)}")
        if x.ndim != 2 or x.shape[-1] != params.n:
            raise ValueError(f"field {name} must have shape (B, n={params.n}), got {tuple(x.shape)}")
    if u.shape != v.shape or u.dtype != v.dtype or u.device != v.device:
        raise ValueError(
            f"fields u and v must match in shape, dtype and device, got {tuple(u.shape)}/{u.dtype} and {tuple(v.shape)}/{v.dtype}"
        )
    # NaN and infinities carry through the sum into the peak, so one reduction and one host
    # sync serve both checks; the slower check that names the cavities runs only on failure
    # (adding the two parts by hand: in eager mode a sum over the size-2 last axis is slower)
    ru, rv = torch.view_as_real(u).square(), torch.view_as_real(v).square()
    peak = (ru[..., 0] + ru[..., 1] + rv[..., 0] + rv[..., 1]).amax(-1)
    if not bool((peak <= MAX_PEAK_POWER).all()):
        check_finite(u, v, " (input)")
        rows = (peak > MAX_PEAK_POWER).nonzero().flatten().tolist()
        raise ValueError(f"field of {_cavities(rows)} has peak power "
                         f"{float(peak[rows[0]]):.3g} > MAX_PEAK_POWER = {MAX_PEAK_POWER:g}")


def as_batch(x, batch: int, name: str, like: torch.Tensor, width: int | None = None) -> torch.Tensor:
    """Broadcast a scalar (or (width,) vector) to (B,) or (B, width) real, checking the shape."""
    if not torch.is_tensor(x):  # python floats stay float64 until cast below
        x = torch.as_tensor(np.asarray(x, dtype=np.float64) if not isinstance(x, complex) else x)
    x = x.to(device=like.device)
    if x.is_complex():
        raise ValueError(f"{name} must be real, got {x.dtype}")
    x = x.to(_real_dtype(like.dtype))
    want = (batch,) if width is None else (batch, width)
    shared = tuple(x.shape) != want  # one value for every cavity, broadcast below
    if shared and not (x.ndim == (0 if width is None else 1) and (width is None or x.shape[-1] == width)):
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
    if shared:
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"{name} must be finite, got {x.tolist()}")
        return x.expand(want)
    bad = ~(torch.isfinite(x) if width is None else torch.isfinite(x).all(-1))
    if bool(bad.any()):
        rows = bad.nonzero().flatten().tolist()
        raise ValueError(f"{name} of {_cavities(rows)} must be finite, got {x[rows[0]].tolist()}")
    return x


def check_cavity(cavity, batch: int, params: CavityParams) -> torch.Tensor | None:
    """None, or ``cavity`` as a (batch, 5) float64 tensor of per-cavity D, E0, tau, g0, Gamma
    (``CAVITY_KEYS``) within the limits ``CavityParams`` sets; an error names the parameter and
    the cavities. Needs ``params.integrator == "split"``."""
    if cavity is None:
        return None
    if params.integrator != "split":
        raise ValueError(f"per-cavity parameters need integrator='split', got {params.integrator!r}")
    cavity = torch.as_tensor(cavity)
    if cavity.shape != (batch, len(CAVITY_KEYS)) or cavity.is_complex():
        raise ValueError(f"cavity must be real with shape ({batch}, {len(CAVITY_KEYS)}) ({', '.join(CAVITY_KEYS)}), "
                         f"got {tuple(cavity.shape)} {cavity.dtype}")
    cavity = cavity.to(torch.float64)
    # the bounds CavityParams sets: E0 > 0; tau, g0, Gamma >= 0; D any finite value
    strictly_positive = {"E0": True, "tau": False, "g0": False, "Gamma": False}
    for j, name in enumerate(CAVITY_KEYS):
        col = cavity[:, j]
        bad = ~torch.isfinite(col)
        bound = ""
        if name in strictly_positive:
            strict = strictly_positive[name]
            bad |= (col <= 0) if strict else (col < 0)
            bound = " and > 0" if strict else " and >= 0"
        if bool(bad.any()):
            rows = bad.nonzero().flatten().tolist()
            raise ValueError(f"cavity.{name} must be finite{bound}, got {col[bad].tolist()} for {_cavities(rows)}")
    return cavity
