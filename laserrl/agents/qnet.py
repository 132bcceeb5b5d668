"""Q-networks: the paper's (convolutions and max-pooling over the intra-cavity fields, the
waveplate angles joined after the convolutions, then fully connected layers with leaky ReLU,
giving one Q-value per joint action), and one for what instruments measure.

Each network names the observation keys it reads (``in_keys``) and its ``observation``
(``laserrl.envs.laser_env.LaserTask.observation``)."""
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

    in_keys = ("fields", "angles")
    observation = "fields"

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
        q = self.head(torch.cat([x, angle_encoding(angles.reshape(-1, 4))], dim=-1))
        return q.reshape(*lead, self.num_actions)


def angle_encoding(a: torch.Tensor) -> torch.Tensor:
    """(sin 2a, cos 2a) of angles in radians, last axis doubled: continuous across the wrap at +-90 deg."""
    return torch.cat([torch.sin(2 * a), torch.cos(2 * a)], dim=-1)


class MeasuredQNet(nn.Module):
    """Q(s, .) for s = what instruments read (``laserrl.physics.instruments``), the last
    ``history`` observations of each key stacked along its last axis (oldest first):
    ``spectrum`` (..., history * bins) OSA powers, ``energy`` (..., history) the pulse energy W,
    ``autocorrelation`` (..., history * points) if ``points``, ``angles`` (..., history * 4).

    Each observation enters as log10 of the spectrum's shape S_j / sum S (floored at 1e-9),
    log10 W, the autocorrelation as read and the angles as (sin 2a, cos 2a); the stacked
    observations, joined, pass fully connected layers with leaky ReLU (``hidden``).
    """

    observation = "measured"

    def __init__(self, num_actions: int, bins: int, points: int = 0, history: int = 1,
                 hidden: Sequence[int] = (256, 128), negative_slope: float = 0.01):
        super().__init__()
        if num_actions < 1:
            raise ValueError(f"num_actions must be >= 1, got {num_actions}")
        for name, value, low in (("bins", bins, 1), ("points", points, 0), ("history", history, 1)):
            if int(value) != value or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        self.num_actions, self.bins, self.points, self.history = int(num_actions), int(bins), int(points), int(history)
        self.in_keys = ("spectrum", "energy", *(("autocorrelation",) if points else ()), "angles")
        width = self.history * (self.bins + 1 + self.points + 8)
        head: list[nn.Module] = []
        for h in hidden:
            head += [nn.Linear(width, int(h)), nn.LeakyReLU(negative_slope)]
            width = int(h)
        head.append(nn.Linear(width, num_actions))
        self.head = nn.Sequential(*head)

    def features(self, spectrum, energy, *rest) -> torch.Tensor:
        """The joined, scaled observations (..., history * (bins + 1 + points + 8))."""
        angles = rest[-1]
        lead, H = angles.shape[:-1], self.history
        s = spectrum.reshape(*lead, H, self.bins)
        shape = torch.log10(s.clamp_min(0) / s.clamp_min(0).sum(-1, keepdim=True).clamp_min(1e-30) + 1e-9)
        parts = [shape, torch.log10(energy.reshape(*lead, H, 1).clamp_min(1e-9))]
        if self.points:
            parts.append(rest[0].reshape(*lead, H, self.points))
        parts.append(angle_encoding(angles.reshape(*lead, H, 4)))
        return torch.cat(parts, dim=-1).reshape(*lead, -1)

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        if len(obs) != len(self.in_keys):
            raise ValueError(f"MeasuredQNet reads {list(self.in_keys)}, got {len(obs)} tensors")
        return self.head(self.features(*obs))


class RecurrentMeasuredQNet(nn.Module):
    """Q(h_t, .) with a memory: ``MeasuredQNet``'s scaled observations pass a fully connected
    layer (``hidden[0]``, leaky ReLU), a GRU (TorchRL's ``GRUModule``) keeps the hidden state
    h_t = GRU(embedding_t, h_{t-1}) across the steps of an episode, and the remaining layers
    (``hidden[1:]``) map h_t to one Q-value per joint action.

    The env carries h (``recurrent_state``, TorchRL's ``TensorDictPrimer``) and marks the first
    step of each episode (``is_init``, ``InitTracker``), where the GRU starts from zero
    (``laserrl.envs.factory.make_env`` with ``env.gru_size``). Acting runs one step at a time;
    learning runs the GRU over stored sequences from their first step's stored h, inside
    ``torchrl.modules.set_recurrent_mode(True)``. ``td_module()`` is the network as a
    TensorDict module writing ``action_value``.
    """

    observation = "measured"
    recurrent = True

    def __init__(self, num_actions: int, bins: int, points: int = 0, history: int = 1, gru_size: int = 64,
                 hidden: Sequence[int] = (256, 128), negative_slope: float = 0.01):
        super().__init__()
        from torchrl.modules import GRUModule

        if int(gru_size) != gru_size or gru_size < 1:
            raise ValueError(f"gru_size must be an integer >= 1, got {gru_size!r}")
        if not hidden:
            raise ValueError("hidden needs at least one width (the layer before the GRU)")
        # the observation scaling of the feed-forward network (its head is replaced below)
        self.observations = MeasuredQNet(num_actions, bins, points, history, hidden=(), negative_slope=negative_slope)
        del self.observations.head
        self.num_actions, self.gru_size = int(num_actions), int(gru_size)
        self.obs_keys = self.observations.in_keys
        self.in_keys = (*self.obs_keys, "recurrent_state", "is_init")
        width = self.observations.history * (bins + 1 + points + 8)
        self.embed = nn.Sequential(nn.Linear(width, int(hidden[0])), nn.LeakyReLU(negative_slope))
        self.gru = GRUModule(input_size=int(hidden[0]), hidden_size=self.gru_size, in_keys=["embedding", "recurrent_state"],
                             out_keys=["memory", ("next", "recurrent_state")])
        head: list[nn.Module] = []
        width = self.gru_size
        for h in hidden[1:]:
            head += [nn.Linear(width, int(h)), nn.LeakyReLU(negative_slope)]
            width = int(h)
        head.append(nn.Linear(width, num_actions))
        self.head = nn.Sequential(*head)

    def embedding(self, *obs: torch.Tensor) -> torch.Tensor:
        return self.embed(self.observations.features(*obs))

    def td_module(self):
        """observations -> ``embedding`` -> GRU (``memory``, next ``recurrent_state``) -> ``action_value``."""
        from tensordict.nn import TensorDictModule, TensorDictSequential

        return TensorDictSequential(TensorDictModule(self.embedding, in_keys=list(self.obs_keys), out_keys=["embedding"]),
                                    self.gru, TensorDictModule(self.head, in_keys=["memory"], out_keys=["action_value"]))

    def make_primer(self):
        """The env transform that carries the GRU's hidden state from step to step (zeros at a reset)."""
        return self.gru.make_tensordict_primer()

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        raise TypeError("RecurrentMeasuredQNet keeps a state between steps: run it as td_module() on an env "
                        "that carries recurrent_state and is_init")
