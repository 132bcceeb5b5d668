"""Initial intra-cavity fields."""
from __future__ import annotations

import torch

from laserrl.physics.params import CavityParams

__all__ = ["sech_fields", "noise_fields"]


def sech_fields(batch: int, params: CavityParams, amplitude: float = 0.5, width: float = 2.0,
                dtype: torch.dtype = torch.complex64, device=None):
    """u = v = amplitude * sech(t / width), the paper's initial condition (0.5 sech(t/2))."""
    t = params.time_grid(dtype=torch.float64)
    pulse = (amplitude / torch.cosh(t / width)).to(device=device)
    u = pulse.to(dtype).expand(batch, -1).clone()
    return u, u.clone()


def noise_fields(batch: int, params: CavityParams, generator: torch.Generator | None = None, scale: float = 0.1,
                 dtype: torch.dtype = torch.complex64, device=None):
    """Seeded complex Gaussian noise of standard deviation ``scale`` per component."""
    real = torch.float64 if dtype == torch.complex128 else torch.float32
    dev = generator.device if generator is not None else device
    parts = torch.randn((4, batch, params.n), generator=generator, dtype=real, device=dev) * scale
    u = torch.complex(parts[0], parts[1])
    v = torch.complex(parts[2], parts[3])
    return u.to(device), v.to(device)
