"""The FFT helpers that carry planar (real, imaginary) parts into and out of torch.fft: the
bit-packed complex64 path (`fft_bits`) and the `fft_planar` custom op."""
import math

import pytest
import torch

from laserrl.physics.fft_layout import _pack_bits, _unpack_bits, fft_bits, fft_planar

SPECIAL = [0.0, -0.0, 1.0, -1.5, 1e-42, -1e-42, 3.4e38, -3.4e38, math.inf, -math.inf, math.nan]


def test_packed_bits_are_the_complex64_memory_and_unpack_exactly():
    g = torch.Generator().manual_seed(0)
    re = torch.cat([torch.tensor(SPECIAL), torch.randn(53, generator=g)]).reshape(2, 32)
    im = torch.cat([torch.randn(53, generator=g), torch.tensor(SPECIAL[::-1])]).reshape(2, 32)
    bits = _pack_bits(re, im)
    assert bits.dtype == torch.int64 and bits.shape == re.shape
    z = bits.view(torch.complex64)
    # bit-for-bit, so that -0.0, subnormals, infinities and NaN payloads survive
    assert torch.equal(z.real.view(torch.int32), re.view(torch.int32))
    assert torch.equal(z.imag.view(torch.int32), im.view(torch.int32))
    back_re, back_im = _unpack_bits(bits)
    assert torch.equal(back_re.view(torch.int32), re.view(torch.int32))
    assert torch.equal(back_im.view(torch.int32), im.view(torch.int32))


@pytest.mark.parametrize("inverse", [False, True])
def test_fft_ops_equal_torch_fft(inverse):
    g = torch.Generator().manual_seed(1)
    re, im = torch.randn(3, 2, 64, generator=g), torch.randn(3, 2, 64, generator=g)
    want = (torch.fft.ifft if inverse else torch.fft.fft)(torch.complex(re, im))
    got = fft_bits(_pack_bits(re, im), inverse).view(torch.complex64)
    assert torch.equal(got, want)
    pr, pi = fft_planar(re, im, inverse)
    assert torch.equal(pr, want.real) and torch.equal(pi, want.imag)
