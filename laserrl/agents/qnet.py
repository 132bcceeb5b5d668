"""Q-networks: the paper's (convolutions and max-pooling over the intra-cavity fields, the
waveplate angles joined after the convolutions, then fully connected layers with leaky ReLU,
giving one Q-value per joint action), and two for what instruments measure: feed-forward over the
last readings, and with a GRU's memory of the episode.

Each ends in a Q-head (``q_head``): ``joint``, the paper's, one output per joint action; or
``additive``, one value per move of each angle, summed over the angles (``AdditiveActionValues``).

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
        head: ``joint`` or ``additive`` (``q_head``).

    The angles enter as (sin 2a, cos 2a): the optics have period pi in every angle,
    so the encoding is continuous across the wrap at +-90 deg.
    """

    in_keys = ("fields", "angles")
    observation = "fields"

    def __init__(self, num_actions: int, n: int = 256, channels: Sequence[int] = (16, 32, 32), kernel_size: int = 5,
                 pool: int = 2, hidden: Sequence[int] = (128, 64), negative_slope: float = 0.01, head: str = "joint"):
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
        self.head = q_head(flat + 8, hidden, num_actions, negative_slope, head)
        self.num_actions = num_actions
        self.n = n

    def forward(self, fields: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
        lead = fields.shape[:-2]
        x = self.features(fields.reshape(-1, 4, fields.shape[-1])).flatten(1)
        q = self.head(torch.cat([x, angle_encoding(angles.reshape(-1, 4))], dim=-1))
        return q.reshape(*lead, self.num_actions)


def leaky_mlp(width: int, hidden: Sequence[int], out: int, negative_slope: float) -> nn.Sequential:
    """Linear layers of widths ``hidden``, each followed by leaky ReLU, then a linear layer to ``out``."""
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(width, int(h)), nn.LeakyReLU(negative_slope)]
        width = int(h)
    layers.append(nn.Linear(width, out))
    return nn.Sequential(*layers)


HEADS = ("joint", "additive")


def saved_head(config) -> str:
    """The Q-head of a saved run config (``agent.network.head``); ``joint`` for configs saved
    before the key existed."""
    return (((config or {}).get("agent") or {}).get("network") or {}).get("head", "joint")


def controlled_count(num_actions: int) -> int:
    """m for 3^m joint actions (``laserrl.envs.actions``); ValueError if ``num_actions`` is no power of 3."""
    m = 0
    while 3**m < num_actions:
        m += 1
    if 3**m != num_actions:
        raise ValueError(f"num_actions must be a power of 3 (3^m joint actions of m angles), got {num_actions}")
    return m


class AdditiveActionValues(nn.Module):
    """Q(s, a) = V(s) + sum_j [A_j(s, d_j) - mean_d A_j(s, d)], from the 1 + 3m values
    (V, then A_j for the moves d = down, hold, up of each controlled angle j) to one value per joint
    action a = (d_1, ..., d_m) (``laserrl.envs.actions``' encoding: 3^m values).

    A plate turn of one step changes the cavity's output to first order by a sum over the angles, and
    the greedy action of such a Q is each angle's best move on its own: all-hold wherever no single
    angle gains by moving, one choice among 3 per angle rather than one among 3^m. The mean over each
    angle's moves is taken out so that V is the mean joint action's value (a dueling head, one per angle).
    """

    def __init__(self, m: int):
        super().__init__()
        if int(m) != m or m < 1:
            raise ValueError(f"m must be an integer >= 1, got {m!r}")
        self.m = int(m)
        digits = (torch.arange(3**self.m)[:, None] // 3 ** torch.arange(self.m)) % 3  # (3^m, m)
        # column of each angle's move among the 3m advantages. Not a buffer: it follows from m, and an
        # integer buffer would be averaged with the weights (agent.average_decay)
        self._index = digits + 3 * torch.arange(self.m)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != 1 + 3 * self.m:
            raise ValueError(f"AdditiveActionValues({self.m}) reads {1 + 3 * self.m} values, got {x.shape[-1]}")
        adv = x[..., 1:].unflatten(-1, (self.m, 3))
        adv = (adv - adv.mean(-1, keepdim=True)).flatten(-2)
        if self._index.device != x.device:
            self._index = self._index.to(x.device)
        return x[..., :1] + adv[..., self._index].sum(-1)


def q_head(width: int, hidden: Sequence[int], num_actions: int, negative_slope: float, head: str = "joint") -> nn.Sequential:
    """The fully connected layers (``hidden``, leaky ReLU) that end a Q-network: ``joint`` with one
    output per joint action (the paper's); ``additive`` with 1 + 3m outputs made into the 3^m joint
    values by ``AdditiveActionValues``. The last Linear layer is the last weighted layer either way."""
    if head == "joint":
        return leaky_mlp(width, hidden, num_actions, negative_slope)
    if head == "additive":
        m = controlled_count(num_actions)
        return nn.Sequential(*leaky_mlp(width, hidden, 1 + 3 * m, negative_slope), AdditiveActionValues(m))
    raise ValueError(f"head must be one of {list(HEADS)}, got {head!r}")


def angle_encoding(a: torch.Tensor) -> torch.Tensor:
    """(sin 2a, cos 2a) of angles in radians, last axis doubled: continuous across the wrap at +-90 deg."""
    return torch.cat([torch.sin(2 * a), torch.cos(2 * a)], dim=-1)


class MeasuredFeatures(nn.Module):
    """What instruments read (``laserrl.physics.instruments``), scaled and joined: the last ``history``
    observations of each of ``in_keys`` stacked along its last axis (oldest first), ``spectrum``
    (..., history * bins), ``energy`` (..., history), ``autocorrelation`` (..., history * points) if
    ``points``, ``angles`` (..., history * 4), give (..., ``width``) = history * (bins + 1 + points + 8):
    log10 of the spectrum's shape S_j / sum S (floored at 1e-9), log10 W, the autocorrelation as read
    and the angles as (sin 2a, cos 2a)."""

    def __init__(self, bins: int, points: int = 0, history: int = 1):
        super().__init__()
        for name, value, low in (("bins", bins, 1), ("points", points, 0), ("history", history, 1)):
            if int(value) != value or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        self.bins, self.points, self.history = int(bins), int(points), int(history)
        self.in_keys = ("spectrum", "energy", *(("autocorrelation",) if points else ()), "angles")
        self.width = self.history * (self.bins + 1 + self.points + 8)

    def forward(self, spectrum, energy, *rest) -> torch.Tensor:
        angles = rest[-1]
        lead, H = angles.shape[:-1], self.history
        s = spectrum.reshape(*lead, H, self.bins)
        shape = torch.log10(s.clamp_min(0) / s.clamp_min(0).sum(-1, keepdim=True).clamp_min(1e-30) + 1e-9)
        parts = [shape, torch.log10(energy.reshape(*lead, H, 1).clamp_min(1e-9))]
        if self.points:
            parts.append(rest[0].reshape(*lead, H, self.points))
        parts.append(angle_encoding(angles.reshape(*lead, H, 4)))
        return torch.cat(parts, dim=-1).reshape(*lead, -1)


class MeasuredQNet(nn.Module):
    """Q(s, .) for s = the last ``history`` readings of the instruments, scaled and joined
    (``MeasuredFeatures``), passed through fully connected layers with leaky ReLU (``hidden``)."""

    observation = "measured"

    def __init__(self, num_actions: int, bins: int, points: int = 0, history: int = 1,
                 hidden: Sequence[int] = (256, 128), negative_slope: float = 0.01, head: str = "joint"):
        super().__init__()
        if num_actions < 1:
            raise ValueError(f"num_actions must be >= 1, got {num_actions}")
        self.features = MeasuredFeatures(bins, points, history)
        self.num_actions, self.bins, self.points, self.history = int(num_actions), int(bins), int(points), int(history)
        self.in_keys = self.features.in_keys
        self.head = q_head(self.features.width, hidden, num_actions, negative_slope, head)

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        if len(obs) != len(self.in_keys):
            raise ValueError(f"MeasuredQNet reads {list(self.in_keys)}, got {len(obs)} tensors")
        return self.head(self.features(*obs))


def is_recurrent(qnet) -> bool:
    """Whether ``qnet`` keeps a state between steps (``RecurrentMeasuredQNet``)."""
    return bool(getattr(qnet, "recurrent", False))


def gru_core(input_size: int, gru_size: int):
    """TorchRL's ``GRUModule`` of a recurrent Q-network: ``embedding`` and ``recurrent_state`` in,
    ``memory`` and next ``recurrent_state`` out (its primer names the state the env carries)."""
    from torchrl.modules import GRUModule

    return GRUModule(input_size=int(input_size), hidden_size=int(gru_size), in_keys=["embedding", "recurrent_state"],
                     out_keys=["memory", ("next", "recurrent_state")])


class RecurrentMeasuredQNet(nn.Module):
    """Q(h_t, .) with a memory: the scaled observations (``MeasuredFeatures``) pass a fully connected
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
                 hidden: Sequence[int] = (256, 128), negative_slope: float = 0.01, head: str = "joint"):
        super().__init__()
        if int(gru_size) != gru_size or gru_size < 1:
            raise ValueError(f"gru_size must be an integer >= 1, got {gru_size!r}")
        if not hidden:
            raise ValueError("hidden needs at least one width (the layer before the GRU)")
        if num_actions < 1:
            raise ValueError(f"num_actions must be >= 1, got {num_actions}")
        self.features = MeasuredFeatures(bins, points, history)
        self.num_actions, self.gru_size = int(num_actions), int(gru_size)
        self.obs_keys = self.features.in_keys
        self.in_keys = (*self.obs_keys, "recurrent_state", "is_init")
        self.embed = nn.Sequential(nn.Linear(self.features.width, int(hidden[0])), nn.LeakyReLU(negative_slope))
        self.gru = gru_core(hidden[0], self.gru_size)
        self.head = q_head(self.gru_size, hidden[1:], num_actions, negative_slope, head)

    def embedding(self, *obs: torch.Tensor) -> torch.Tensor:
        return self.embed(self.features(*obs))

    def td_module(self):
        """observations -> ``embedding`` -> GRU (``memory``, next ``recurrent_state``) -> ``action_value``."""
        from tensordict.nn import TensorDictModule, TensorDictSequential

        return TensorDictSequential(TensorDictModule(self.embedding, in_keys=list(self.obs_keys), out_keys=["embedding"]),
                                    self.gru, TensorDictModule(self.head, in_keys=["memory"], out_keys=["action_value"]))

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        raise TypeError("RecurrentMeasuredQNet keeps a state between steps: run it as td_module() on an env "
                        "that carries recurrent_state and is_init")
