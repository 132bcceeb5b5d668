"""Memory layouts of the Fourier-space fields u^, v^ around torch.fft.

Contract: every helper computes torch's (I)FFT along the last axis,

    F[x]_k = sum_j x_j exp(-2 pi i j k / n),   F^-1[X]_j = (1/n) sum_k X_k exp(2 pi i j k / n),

of a complex tensor that is held either as planar real parts (re, im) (``fft_planar``,
a custom op) or, for complex64, as the int64 bit patterns of its memory (``fft_bits``,
with ``_pack_bits`` / ``_unpack_bits``), and returns the result in the same layout, bit
for bit what ``torch.fft`` returns. ``_uses_bits`` decides which layout an integrator uses.
"""
from __future__ import annotations

import sys

import torch

__all__ = ["fft_planar", "fft_bits"]


@torch.library.custom_op("laserrl::fft_planar", mutates_args=())
def fft_planar(re: torch.Tensor, im: torch.Tensor, inverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(I)FFT along the last axis of re + i im, returned as contiguous planar (re, im).

    A custom op so that, inside a compiled graph, Inductor sees an extern kernel with
    contiguous real outputs: reading the real and imaginary parts of a complex FFT output
    directly makes Inductor generate strided, scalar (and for reductions, transposing)
    loops that are slower than the FFT itself.
    """
    z = torch.complex(re, im)
    z = torch.fft.ifft(z) if inverse else torch.fft.fft(z)
    return z.real.contiguous(), z.imag.contiguous()


@fft_planar.register_fake
def _(re, im, inverse):
    return torch.empty_like(re), torch.empty_like(im)


def fft_bits(bits: torch.Tensor, inverse: bool) -> torch.Tensor:
    """(I)FFT along the last axis of complex64 data held as int64 bit patterns (``_pack_bits``).

    A complex64 and an int64 are both 8 bytes, so the tensor is reinterpreted, not copied,
    on the way in and out. Inside a compiled graph the packing and unpacking of the planar
    float32 parts are then plain contiguous integer operations that Inductor vectorises and
    fuses into the neighbouring kernels, instead of the strided copies that interleaving and
    de-interleaving cost around ``fft_planar``. Plain ATen calls rather than a custom op:
    Inductor passes the dtype views and the FFT through as extern calls, without the
    per-call dispatch of a Python custom op.
    """
    z = bits.view(torch.complex64)
    z = torch.fft.ifft(z) if inverse else torch.fft.fft(z)
    return z.view(torch.int64)


def _pack_bits(re: torch.Tensor, im: torch.Tensor) -> torch.Tensor:
    """float32 (re, im) -> int64 whose memory is the complex64 re + i im (little-endian:
    the real part in the low 32 bits)."""
    return (re.view(torch.int32).to(torch.int64) & 0xFFFFFFFF) | (im.view(torch.int32).to(torch.int64) << 32)


def _unpack_bits(bits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of ``_pack_bits``. The shifts sign-extend each half, so that the conversion
    to int32 is exact (no out-of-range narrowing)."""
    re = ((bits << 32) >> 32).to(torch.int32).view(torch.float32)
    im = (bits >> 32).to(torch.int32).view(torch.float32)
    return re, im


#: complex64 memory holds the real part first; ``_pack_bits`` puts it in the low 32 bits.
_LITTLE_ENDIAN = sys.byteorder == "little"


def _uses_bits(real_dtype: torch.dtype, device: torch.device, compiled: bool) -> bool:
    """Whether the FFTs take the bit-packed path (``fft_bits``). It pays off only when Inductor
    fuses the packing (in eager mode each integer op would be a pass of its own) and needs
    complex64 in little-endian memory. CPU only: the strided copies it avoids are a CPU
    problem."""
    return compiled and real_dtype == torch.float32 and device.type == "cpu" and _LITTLE_ENDIAN


def _fft_any(re: torch.Tensor, im: torch.Tensor, inverse: bool):
    if _uses_bits(re.dtype, re.device, torch.compiler.is_compiling()):
        return _unpack_bits(fft_bits(_pack_bits(re, im), inverse))
    return fft_planar(re, im, inverse)


def _ifft_planar(re: torch.Tensor, im: torch.Tensor):
    return _fft_any(re, im, True)


def _fft_planar(re: torch.Tensor, im: torch.Tensor):
    return _fft_any(re, im, False)
