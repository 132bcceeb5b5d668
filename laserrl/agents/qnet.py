"""Q-network of the paper: convolutions and max-pooling over the intra-cavity
fields, the waveplate angles joined after the convolutions, then fully connected
layers with leaky ReLU, giving one Q-value per joint action."""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


class FieldQNet(nn.Module):
    """Q(s, .) for s = (fields (..., 4, n), angles (..., 4) in radians).

    Args:
        num_actions: 3^m for m controlled angles.
        n: samples per field.
        channels: output channels of each Conv1d (kernel ``kernel_size``, 'same'
            padding), each followed by leaky ReLU and MaxPool1d(``pool``).
        hidden: widths of the fully connected layers after the join.
        negative_slope: leaky ReLU slope.

    The angles enter as (sin 2a, cos 2a): the optics have period pi in every angle,
    so the encoding is continuous across the wrap at +-90 deg.
    """

    def __init__(self, num_actions: int, n: int = 256, channels: Sequence[int] = (16, 32, 32), kernel_size: int = 5,
                 pool: int = 2, hidden: Sequence[int] = (128, 64), negative_slope: float = 0.01):
        super().__init__()
        if num_actions < 1:
            raise ValueError(f"num_actions must be >= 1, got {num_actions}")
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be a positive odd number, got {kernel_size}")
        if pool < 1 or n // pool ** len(channels) < 1:
            raise ValueError(f"pool={pool} with {len(channels)} conv layers leaves no samples of n={n}")
        layers: list[nn.Module] = []
        in_ch = 4
        for ch in channels:
            layers += [nn.Conv1d(in_ch, int(ch), kernel_size, padding=kernel_size // 2),
                       nn.LeakyReLU(negative_slope), nn.MaxPool1d(pool)]
            in_ch = int(ch)
        self.features = nn.Sequential(*layers)
        flat = in_ch * (n // pool ** len(channels))
        head: list[nn.Module] = []
        width = flat + 8
        for h in hidden:
            head += [nn.Linear(width, int(h)), nn.LeakyReLU(negative_slope)]
            width = int(h)
        head.append(nn.Linear(width, num_actions))
        self.head = nn.Sequential(*head)
        self.num_actions = num_actions
        self.n = n

    def forward(self, fields: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
        lead = fields.shape[:-2]
        x = self.features(fields.reshape(-1, 4, fields.shape[-1])).flatten(1)
        a = angles.reshape(-1, 4)
        enc = torch.cat([torch.sin(2 * a), torch.cos(2 * a)], dim=-1)
        q = self.head(torch.cat([x, enc], dim=-1))
        return q.reshape(*lead, self.num_actions)
