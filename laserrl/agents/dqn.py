"""Builders that assemble TorchRL's DQN parts for the laser env.

Everything here is TorchRL's own: ``QValueActor``, ``EGreedyModule``, ``DQNLoss``
(double DQN, delayed target), ``SoftUpdate``/``HardUpdate``, and the (prioritized)
replay buffers, and ``MultiStepTransform`` for n-step returns. The only thing added is
the exponential epsilon decay the paper uses, which sets ``EGreedyModule.eps`` from the
frame count; and torch's ``AveragedModel`` for an average of the weights that acts greedily
(``agent.average_decay``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from torchrl.data import LazyTensorStorage, TensorDictPrioritizedReplayBuffer, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.envs.transforms import MultiStepTransform
from torchrl.modules import EGreedyModule, QValueActor, set_recurrent_mode
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate

from laserrl.agents.qnet import HEADS, FieldQNet, MeasuredQNet, RecurrentMeasuredQNet, is_recurrent
from laserrl.validate import ConfigError, check_number, check_numbers, check_one_of


def make_qnet(num_actions: int, n: int, channels, kernel_size: int, pool: int, hidden, negative_slope: float,
              head: str = "joint") -> FieldQNet:
    """The Q-network of the ``agent.network`` config; bad values raise a ConfigError naming the key."""
    channels = check_numbers(channels, "agent.network.channels", low=1, integer=True)
    hidden = check_numbers(hidden, "agent.network.hidden", low=1, integer=True)
    kernel_size = check_number(kernel_size, "agent.network.kernel_size", low=1, integer=True)
    pool = check_number(pool, "agent.network.pool", low=1, integer=True)
    negative_slope = check_number(negative_slope, "agent.network.negative_slope", low=0)
    try:
        return FieldQNet(num_actions, n=n, channels=tuple(channels), kernel_size=kernel_size, pool=pool,
                         hidden=tuple(hidden), negative_slope=negative_slope, head=head)
    except ValueError as err:  # combinations only the network can judge (odd kernel, pooling vs n)
        raise ConfigError(f"agent.network: {err}") from None


def make_measured_qnet(num_actions: int, env_cfg, hidden, negative_slope: float,
                       head: str = "joint") -> MeasuredQNet | RecurrentMeasuredQNet:
    """The Q-network for ``env.observation=measured``: its inputs from ``env.instruments`` and
    ``env.history``, its layers from ``agent.network.hidden`` and ``negative_slope``; with
    ``env.gru_size`` a GRU of that size between the first layer and the rest."""
    from laserrl.envs.factory import gru_size, history_length

    hidden = check_numbers(hidden, "agent.network.hidden", low=1, integer=True)
    negative_slope = check_number(negative_slope, "agent.network.negative_slope", low=0)
    from laserrl.physics.instruments import Instruments

    try:
        ins = Instruments(**dict(env_cfg.get("instruments") or {}))  # its defaults for the settings not given
        shape = dict(bins=ins.spectrum_bins, points=ins.autocorrelation_points, history=history_length(env_cfg),
                     hidden=tuple(hidden), negative_slope=negative_slope, head=head)
        memory = gru_size(env_cfg)
        if memory is not None:
            return RecurrentMeasuredQNet(num_actions, gru_size=memory, **shape)
        return MeasuredQNet(num_actions, **shape)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"env.instruments: {err}") from None


def build_qnet(num_actions: int, env_cfg, network) -> FieldQNet | MeasuredQNet | RecurrentMeasuredQNet:
    """The Q-network for an env of config ``env_cfg`` (its ``observation``, grid, instruments and
    history) with ``num_actions`` joint actions and the ``agent.network`` config ``network`` (a
    config without ``head``, as saved before the key existed, has the paper's joint head)."""
    head = check_one_of(network.get("head", "joint"), "agent.network.head", HEADS)
    observation = env_cfg.get("observation", "fields")
    if observation == "measured":
        return make_measured_qnet(num_actions, env_cfg, network["hidden"], network["negative_slope"], head)
    from laserrl.envs.factory import gru_size, history_length

    if history_length(env_cfg) != 1:
        raise ConfigError("env.history > 1 needs env.observation=measured (the fields network sees one state)")
    if gru_size(env_cfg) is not None:
        raise ConfigError("env.gru_size needs env.observation=measured (the fields network has no memory)")
    return make_qnet(num_actions, int((env_cfg.get("physics") or {}).get("n", 256)), network["channels"],
                     network["kernel_size"], network["pool"], network["hidden"], network["negative_slope"], head)


def make_actor(qnet: FieldQNet | MeasuredQNet | RecurrentMeasuredQNet, action_spec) -> QValueActor:
    """Greedy Q-actor reading the network's ``in_keys``; ``action_spec`` is the env's unbatched action spec."""
    if is_recurrent(qnet):
        return QValueActor(qnet.td_module(), spec=action_spec)
    keys = list(qnet.in_keys)
    module = TensorDictModule(qnet, in_keys=keys, out_keys=["action_value"])
    return QValueActor(module, in_keys=keys, spec=action_spec)


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
        check_one_of(self.kind, "agent.exploration.kind", ("exponential", "linear"))
        check_number(self.start, "agent.exploration.start", low=0, high=1)
        check_number(self.end, "agent.exploration.end", low=0, high=self.start)
        check_number(self.decay_frames, "agent.exploration.decay_frames", low=0, low_open=True)

    def __call__(self, frames: int) -> float:
        if self.kind == "exponential":
            return self.end + (self.start - self.end) * math.exp(-frames / self.decay_frames)
        return self.start + (self.end - self.start) * min(frames / self.decay_frames, 1.0)


def make_exploration_policy(actor: QValueActor, action_spec, schedule: EpsilonSchedule):
    """actor followed by TorchRL's EGreedyModule; returns (policy, egreedy)."""
    egreedy = EGreedyModule(action_spec, eps_init=float(schedule.start), eps_end=float(schedule.end))
    return TensorDictSequential(actor, egreedy), egreedy


def make_loss(actor: QValueActor, action_spec, gamma: float, loss_function: str = "smooth_l1") -> DQNLoss:
    check_number(gamma, "agent.gamma", low=0, high=1)
    check_one_of(loss_function, "agent.loss_function", ("l1", "l2", "smooth_l1"))
    loss = DQNLoss(actor, loss_function=loss_function, delay_value=True, double_dqn=True, action_space=action_spec)
    loss.make_value_estimator(gamma=gamma)
    return loss


def make_target_updater(loss: DQNLoss, kind: str, tau: float = 0.005, interval: int = 500):
    """SoftUpdate (paper: partial update every step) or HardUpdate every ``interval`` updates."""
    check_one_of(kind, "agent.target.kind", ("soft", "hard"))
    tau = check_number(tau, "agent.target.tau", low=0, high=1, low_open=True)
    interval = check_number(interval, "agent.target.interval", low=1, integer=True)
    if kind == "soft":
        return SoftUpdate(loss, tau=tau)
    return HardUpdate(loss, value_network_update_interval=interval)


def make_replay(kind: str, size: int, batch_size: int, alpha: float = 0.6, beta: float = 0.4, device="cpu",
                sequence: int = 1):
    """TorchRL's prioritized (default) or uniform replay over a flat tensor storage.

    ``sequence`` > 1 (a recurrent agent): each stored item is a sequence of that many steps of one
    cavity (a collector batch's row), ``size`` and ``batch_size`` still count steps, and a
    sequence's priority is the largest TD error along it."""
    check_one_of(kind, "replay.kind", ("prioritized", "uniform"))
    size = check_number(size, "replay.size", low=1, integer=True)
    batch_size = check_number(batch_size, "optim.batch_size", low=1, integer=True)
    alpha = check_number(alpha, "replay.alpha", low=0)
    beta = check_number(beta, "replay.beta", low=0)
    if sequence > 1:
        if batch_size < sequence:
            raise ConfigError(f"optim.batch_size ({batch_size}) must hold at least one sequence of {sequence} steps "
                              "(collector.frames_per_batch / env.num_envs) for a recurrent agent")
        size, batch_size = max(1, size // sequence), batch_size // sequence
    storage = LazyTensorStorage(size, device=device)
    if kind == "prioritized":
        return TensorDictPrioritizedReplayBuffer(alpha=alpha, beta=beta, storage=storage, batch_size=batch_size,
                                                 priority_key="td_error")
    return TensorDictReplayBuffer(storage=storage, sampler=RandomSampler(), batch_size=batch_size)


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
    n_steps = check_number(n_steps, "agent.n_steps", low=1, integer=True)
    return MultiStepTransform(n_steps, gamma) if n_steps > 1 else None


@dataclass
class DQNAgent:
    """The learning parts of a double DQN and one gradient update of them.

    ``qnet`` is the Q-network, ``actor`` its greedy ``QValueActor``, ``policy`` the actor
    followed by ``egreedy`` (epsilon set from ``schedule``), ``loss`` TorchRL's ``DQNLoss``
    (online and delayed target network), ``target`` its soft or hard updater, and
    ``optimizer`` / ``lr_schedule`` Adam with a step-wise learning-rate decay.

    ``averaged`` (with ``agent.average_decay``): an exponential moving average of the
    Q-network's weights over the gradient updates (torch's ``AveragedModel``), whose greedy
    actor ``greedy`` is the one evaluated and saved; without it ``greedy`` is ``actor``.
    Averaging the weights over a few thousand updates smooths the greedy policy, whose choice
    between near-equal actions otherwise flips from one evaluation to the next (Anschel et
    al. 2017, "Averaged-DQN", average Q-estimates for the same reason).
    """

    qnet: FieldQNet | MeasuredQNet | RecurrentMeasuredQNet
    actor: QValueActor
    policy: TensorDictSequential
    egreedy: EGreedyModule
    schedule: EpsilonSchedule
    loss: DQNLoss
    target: SoftUpdate | HardUpdate
    optimizer: torch.optim.Optimizer
    lr_schedule: torch.optim.lr_scheduler.StepLR
    max_grad_norm: float
    prioritized: bool
    averaged: AveragedModel | None
    greedy: QValueActor

    @classmethod
    def build(cls, action_spec, env_cfg, *, network, exploration, gamma: float, loss_function: str, target,
              lr: float, weight_decay: float, lr_decay: float, lr_decay_updates: int, max_grad_norm: float,
              prioritized: bool, average_decay: float | None = None) -> "DQNAgent":
        """The agent for an env with ``action_spec`` (unbatched) and the ``env`` config ``env_cfg``
        (what it observes); the keyword groups are the ``agent`` and ``optim`` config entries."""
        qnet = build_qnet(int(action_spec.n), env_cfg, network)
        lr = check_number(lr, "optim.lr", low=0, low_open=True)
        weight_decay = check_number(weight_decay, "optim.weight_decay", low=0)
        lr_decay = check_number(lr_decay, "optim.lr_decay", low=0, high=1, low_open=True)
        lr_decay_updates = check_number(lr_decay_updates, "optim.lr_decay_updates", low=1, integer=True)
        max_grad_norm = check_number(max_grad_norm, "optim.max_grad_norm", low=0, low_open=True)
        average_decay = check_number(average_decay, "agent.average_decay", low=0, high=1, low_open=True, optional=True)
        if average_decay == 1:
            raise ConfigError("agent.average_decay must be below 1 (1 would never move the average), got 1")
        averaged = None if average_decay is None else AveragedModel(
            qnet, multi_avg_fn=get_ema_multi_avg_fn(float(average_decay)), use_buffers=True)
        actor = make_actor(qnet, action_spec)
        greedy = actor if averaged is None else make_actor(averaged.module, action_spec)
        schedule = EpsilonSchedule(**exploration)
        policy, egreedy = make_exploration_policy(actor, action_spec, schedule)
        loss = make_loss(actor, action_spec, gamma, loss_function)
        updater = make_target_updater(loss, **target)
        optimizer = torch.optim.Adam(loss.parameters(), lr=lr, weight_decay=weight_decay)
        # stepped once per gradient update: lr * lr_decay ** (updates // lr_decay_updates)
        lr_schedule = torch.optim.lr_scheduler.StepLR(optimizer, step_size=int(lr_decay_updates), gamma=float(lr_decay))
        return cls(qnet, actor, policy, egreedy, schedule, loss, updater, optimizer, lr_schedule, float(max_grad_norm),
                   bool(prioritized), averaged, greedy)

    def restart_average(self) -> None:
        """Start the weight average afresh from the Q-network as it is (after a warm start)."""
        if self.averaged is not None:
            self.averaged.module.load_state_dict(self.qnet.state_dict())
            self.averaged.n_averaged.zero_()

    @property
    def greedy_qnet(self) -> torch.nn.Module:
        """The network the greedy actor acts with (evaluated and saved): the average, or the Q-network."""
        return self.averaged.module if self.averaged is not None else self.qnet

    def model_weights(self) -> dict:
        """The weights of the greedy actor that is evaluated and saved: the average, or the Q-network's."""
        return self.greedy_qnet.state_dict()

    def explore(self, frames: int) -> float:
        """Set epsilon for ``frames`` collected so far; returns it."""
        self.egreedy.eps.fill_(self.schedule(frames))
        return float(self.egreedy.eps)

    def update(self, replay) -> float:
        """One gradient step on a batch sampled from ``replay``, then the target update (and,
        for prioritized replay, the new priorities); returns the loss."""
        sample = replay.sample()
        with set_recurrent_mode(is_recurrent(self.qnet)):  # a GRU runs over each stored sequence
            losses = self.loss(sample)
        self.optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.max_grad_norm)
        self.optimizer.step()
        self.lr_schedule.step()
        self.target.step()
        if self.averaged is not None:
            self.averaged.update_parameters(self.qnet)
        if self.prioritized:
            replay.update_tensordict_priority(sample)
        return float(losses["loss"].detach())

    @property
    def lr(self) -> float:
        return float(self.optimizer.param_groups[0]["lr"])

    def target_weights(self) -> dict | None:
        """The target network's weights (for the checkpoint)."""
        params = getattr(self.loss, "target_value_network_params", None)
        return params.state_dict() if params is not None else None

    def learning_state(self) -> dict:
        """What learning needs beyond the Q-network and the optimizer: the loss module (online and
        target network), the learning-rate schedule, epsilon and a hard target update's counter."""
        return {"loss": self.loss.state_dict(), "lr_schedule": self.lr_schedule.state_dict(),
                "egreedy": self.egreedy.state_dict(), "target_counter": getattr(self.target, "counter", None),
                "average": self.averaged.state_dict() if self.averaged is not None else None}

    def load_learning_state(self, state: dict, optimizer_state: dict, updates: int) -> None:
        """Continue from ``learning_state()`` and the optimizer's state of a checkpoint made after
        ``updates`` gradient updates."""
        self.loss.load_state_dict(state["loss"])
        self.optimizer.load_state_dict(optimizer_state)
        if state.get("lr_schedule") is not None:
            self.lr_schedule.load_state_dict(state["lr_schedule"])
        else:  # a checkpoint without a saved schedule had a constant rate: count on from its updates
            self.lr_schedule.last_epoch = int(updates)
        self.egreedy.load_state_dict(state["egreedy"])
        if state["target_counter"] is not None:
            self.target.counter = state["target_counter"]
        if self.averaged is not None and state.get("average") is not None:
            self.averaged.load_state_dict(state["average"])
