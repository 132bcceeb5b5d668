"""Builders that assemble TorchRL's DQN parts for the laser env.

Everything here is TorchRL's own: ``QValueActor``, ``EGreedyModule``, ``DQNLoss``
(double DQN, delayed target), ``SoftUpdate``/``HardUpdate``, and the (prioritized)
replay buffers, and ``MultiStepTransform`` for n-step returns. The only thing added is
the exponential epsilon decay the paper uses, which sets ``EGreedyModule.eps`` from the
frame count.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import LazyTensorStorage, TensorDictPrioritizedReplayBuffer, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.envs.transforms import MultiStepTransform
from torchrl.modules import EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate

from laserrl.agents.qnet import FieldQNet

OBS_KEYS = ["fields", "angles"]


def make_qnet(num_actions: int, n: int, channels, kernel_size: int, pool: int, hidden, negative_slope: float) -> FieldQNet:
    return FieldQNet(num_actions, n=n, channels=tuple(channels), kernel_size=kernel_size, pool=pool,
                     hidden=tuple(hidden), negative_slope=negative_slope)


def make_actor(qnet: FieldQNet, action_spec) -> QValueActor:
    """Greedy Q-actor; ``action_spec`` is the env's unbatched action spec."""
    module = TensorDictModule(qnet, in_keys=OBS_KEYS, out_keys=["action_value"])
    return QValueActor(module, in_keys=OBS_KEYS, spec=action_spec)


@dataclass
class EpsilonSchedule:
    """epsilon(frames): exponential (paper) or linear decay from ``start`` to ``end``.

    exponential: end + (start - end) * exp(-frames / decay_frames)
    linear:      start + (end - start) * min(frames / decay_frames, 1)
    """

    start: float = 1.0
    end: float = 0.05
    decay_frames: float = 5000.0
    kind: str = "exponential"

    def __post_init__(self):
        if self.kind not in ("exponential", "linear"):
            raise ValueError(f"agent.exploration.kind must be 'exponential' or 'linear', got {self.kind!r}")
        if not (0.0 <= self.end <= self.start <= 1.0):
            raise ValueError(f"agent.exploration needs 0 <= end <= start <= 1, got start={self.start}, end={self.end}")
        if not self.decay_frames > 0:
            raise ValueError(f"agent.exploration.decay_frames must be > 0, got {self.decay_frames}")

    def __call__(self, frames: int) -> float:
        if self.kind == "exponential":
            return self.end + (self.start - self.end) * math.exp(-frames / self.decay_frames)
        return self.start + (self.end - self.start) * min(frames / self.decay_frames, 1.0)


def make_exploration_policy(actor: QValueActor, action_spec, schedule: EpsilonSchedule):
    """actor followed by TorchRL's EGreedyModule; returns (policy, egreedy)."""
    egreedy = EGreedyModule(action_spec, eps_init=float(schedule.start), eps_end=float(schedule.end))
    return TensorDictSequential(actor, egreedy), egreedy


def make_loss(actor: QValueActor, action_spec, gamma: float, loss_function: str = "smooth_l1") -> DQNLoss:
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"agent.gamma must be in [0, 1], got {gamma}")
    loss = DQNLoss(actor, loss_function=loss_function, delay_value=True, double_dqn=True, action_space=action_spec)
    loss.make_value_estimator(gamma=gamma)
    return loss


def make_target_updater(loss: DQNLoss, kind: str, tau: float = 0.005, interval: int = 500):
    """SoftUpdate (paper: partial update every step) or HardUpdate every ``interval`` updates."""
    if kind == "soft":
        if not 0.0 < tau <= 1.0:
            raise ValueError(f"agent.target.tau must be in (0, 1], got {tau}")
        return SoftUpdate(loss, tau=tau)
    if kind == "hard":
        if interval < 1:
            raise ValueError(f"agent.target.interval must be >= 1, got {interval}")
        return HardUpdate(loss, value_network_update_interval=interval)
    raise ValueError(f"agent.target.kind must be 'soft' or 'hard', got {kind!r}")


def make_replay(kind: str, size: int, batch_size: int, alpha: float = 0.6, beta: float = 0.4, device="cpu"):
    """TorchRL's prioritized (default) or uniform replay over a flat tensor storage."""
    if size < 1 or batch_size < 1:
        raise ValueError(f"replay.size and optim.batch_size must be >= 1, got {size} and {batch_size}")
    storage = LazyTensorStorage(int(size), device=device)
    if kind == "prioritized":
        return TensorDictPrioritizedReplayBuffer(alpha=alpha, beta=beta, storage=storage, batch_size=batch_size,
                                                 priority_key="td_error")
    if kind == "uniform":
        return TensorDictReplayBuffer(storage=storage, sampler=RandomSampler(), batch_size=batch_size)
    raise ValueError(f"replay.kind must be 'prioritized' or 'uniform', got {kind!r}")


def make_n_step(n_steps: int, gamma: float) -> MultiStepTransform | None:
    """n-step returns, or None for the paper's one-step TD target (``n_steps`` = 1).

    TorchRL's ``MultiStepTransform``: ``transform.inv(batch)`` turns a collector batch of
    shape (..., time) into transitions whose reward is sum_{k<m} gamma^k r_{t+k} and whose
    next observation is the one m = min(n, steps to the episode's end) steps later, with
    ``steps_to_next_obs`` = m, from which ``DQNLoss`` discounts the bootstrap by gamma^m.
    It keeps the last ``n_steps`` steps of the previous batch, so each transition is
    stored once its n steps have been collected (None until then). The laser env's
    episodes only end by truncation, for which bootstrapping from the last state is right.
    """
    if isinstance(n_steps, bool) or not isinstance(n_steps, int) or n_steps < 1:
        raise ValueError(f"agent.n_steps must be an integer >= 1, got {n_steps!r}")
    return MultiStepTransform(n_steps, gamma) if n_steps > 1 else None
