"""Batched discrete-time IIR filters applied one sample per agent step.

Coefficients come from ``scipy.signal.butter`` (bilinear transform of a Butterworth
prototype) with the sampling rate fs = 1 per agent step, so cut-offs are in cycles per
step and must lie in (0, 0.5). Each call filters one new sample of every channel with
``scipy.signal.lfilter`` and carries the filter state (direct form II transposed) to the
next step.
"""
from __future__ import annotations

import numpy as np
from scipy import signal


class StepFilter:
    """Butterworth filter of ``order`` with cut-off ``cutoff`` (cycles/step), kind "high" or "low",
    over channels of shape ``shape`` (e.g. (B,) or (B, m))."""

    def __init__(self, kind: str, cutoff: float, order: int, shape: tuple[int, ...]):
        if kind not in ("high", "low"):
            raise ValueError(f"filter kind must be 'high' or 'low', got {kind!r}")
        self.b, self.a = signal.butter(int(order), float(cutoff), btype=kind, fs=1.0)
        self._zi_unit = signal.lfilter_zi(self.b, self.a)  # steady state for a unit constant input
        self.state = np.zeros((*shape, len(self._zi_unit)))

    def reset(self, x0: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Start in the steady state of a constant input x0 (no start-up transient)."""
        state = np.broadcast_to(np.asarray(x0, dtype=np.float64)[..., None] * self._zi_unit, self.state.shape)
        if mask is not None:  # (B,) cavities to reset, broadcast over the other channel axes
            mask = np.asarray(mask, dtype=bool).reshape(mask.shape + (1,) * (self.state.ndim - np.ndim(mask)))
            state = np.where(mask, state, self.state)
        self.state = np.array(state)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        y, self.state = signal.lfilter(self.b, self.a, np.asarray(x, dtype=np.float64)[..., None], axis=-1,
                                       zi=self.state)
        return y[..., 0]
