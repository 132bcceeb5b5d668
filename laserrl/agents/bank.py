"""A bank of Q-networks trained at different birefringence K, acting as one policy.

K is not observed, so a bank cannot simply pick the model trained nearest the true K.
``MaxQBank`` picks, for every cavity at every step, the model whose greedy Q-value is
highest (each model's estimate of the return it can still collect) and acts with that
model's greedy action. ``TrialBank`` tries the models in turn on the running laser instead:
it keeps a model while the measured reward r rises or holds the lock, and moves on to the
next one when r has not risen over a trial of a few steps (models that read the instruments,
``env.observation=measured``, are judged by the readings' reward ``r_measured``, whose scale
is its own: set ``TrialRule.lock_r`` in it). Neither is told K. The oracle rule that knows
K, ``NearestKBank``, acts with the model trained nearest each cavity's K at every step; it
reads K itself, which only a caller that knows it provides (``laserrl-control`` gives the
simulated K; at fixed K ``laserrl.evaluate.evaluate_bank`` groups the K values by model
instead).

A bank member can itself be an ensemble, ``MeanQ``: several Q-networks trained for the same
task (for example the seeds of one fine-tuning recipe) whose Q-values are averaged. Where the
greedy choice hangs on Q-value differences of a few percent (a lock one angle wide), the
seeds' errors in those differences are partly independent, and their mean picks more
reliably than any one of them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import QValueModule

from laserrl.agents.qnet import FieldQNet, MeasuredQNet, is_recurrent

__all__ = ["MaxQBank", "MeanQ", "NearestKBank", "TrialBank", "TrialRule", "make_bank_actor", "make_nearest_actor",
           "make_trial_actor", "nearest_model"]

#: a Q-network: one model's, or an ensemble's mean (``MeanQ``)
QNet = "FieldQNet | MeasuredQNet | MeanQ"


def _common_action_count(qnets: list[nn.Module], group: str, of_group: str) -> int:
    """The number of actions that all ``qnets`` share; ValueError if there are none or they differ.
    ``group`` / ``of_group`` name the collection in the messages ("a model bank" / "a bank")."""
    if not qnets:
        raise ValueError(f"{group} needs at least one Q-network")
    if any(is_recurrent(q) for q in qnets):
        raise ValueError(f"{group} combines feed-forward Q-networks; a recurrent one (env.gru_size) keeps a state of "
                         "its own that the combined models do not share")
    actions = {q.num_actions for q in qnets}
    if len(actions) != 1:
        raise ValueError(f"all models of {of_group} must have the same number of actions, got {sorted(actions)}")
    return actions.pop()


class MeanQ(nn.Module):
    """The mean of the Q-values of several Q-networks with the same actions (an ensemble)."""

    def __init__(self, qnets: list[nn.Module]):
        super().__init__()
        self.num_actions = _common_action_count(qnets, "an ensemble", "an ensemble")
        self.in_keys = _in_keys(qnets)
        self.observation = qnets[0].observation
        self.qnets = nn.ModuleList(qnets)

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        return torch.stack([net(*obs) for net in self.qnets]).mean(0)


def _in_keys(qnets) -> tuple[str, ...]:
    """The observation keys every network of ``qnets`` reads (they must read the same)."""
    keys = {tuple(net.in_keys) for net in qnets}
    if len(keys) != 1:
        raise ValueError(f"the models read different observations {sorted(keys)}: combine models of one observation")
    return keys.pop()


def _q_of(q: torch.Tensor, model: torch.Tensor) -> torch.Tensor:
    """The Q-values (*batch, A) of the chosen ``model`` (*batch,) per cavity, from all models' (M, *batch, A)."""
    return torch.gather(q, 0, model[None, ..., None].expand(1, *q.shape[1:]))[0]


class MaxQBank(nn.Module):
    """Q-values of the model with the highest max Q, per cavity; and that model's index."""

    def __init__(self, qnets: list[QNet]):
        super().__init__()
        _common_action_count(qnets, "a model bank", "a bank")
        self.qnets = nn.ModuleList(qnets)

    def forward(self, *obs: torch.Tensor):
        q = torch.stack([net(*obs) for net in self.qnets])  # (M, *batch, A)
        model = q.max(-1).values.argmax(0)  # (*batch,)
        return _q_of(q, model), model


def make_bank_actor(qnets: list[QNet], action_spec) -> TensorDictSequential:
    """Greedy policy of a ``MaxQBank``: writes ``action``, ``action_value`` and ``model``."""
    bank = TensorDictModule(MaxQBank(qnets), in_keys=list(_in_keys(qnets)), out_keys=["action_value", "model"])
    return TensorDictSequential(bank, QValueModule(spec=action_spec))


@dataclass(frozen=True)
class TrialRule:
    """How ``TrialBank`` tries its models: each model gets ``steps`` agent steps at a time; it
    stays while r rises by at least ``min_rise`` over such a trial, or while r >= ``lock_r``
    (locked: nothing to search for); otherwise the next model (cyclically) takes over."""

    steps: int = 5
    min_rise: float = 0.002
    lock_r: float = 0.15

    def __post_init__(self):
        from laserrl.validate import check_number

        check_number(self.steps, "bank_trial.steps", low=1, integer=True)
        check_number(self.min_rise, "bank_trial.min_rise", low=0)
        check_number(self.lock_r, "bank_trial.lock_r")


class TrialBank(nn.Module):
    """Per cavity, the Q-values of the model on trial (see ``TrialRule``); and that model's index.

    Reads what an experiment measures, the reward r of the current state, and the step count
    of the episode (0: a new episode, which starts with model 0). Its per-cavity state (the
    model on trial, the steps it has had, r when its trial began) lives in the module, so
    one ``TrialBank`` serves one batch of cavities stepping together."""

    def __init__(self, qnets: list[QNet], rule: TrialRule = TrialRule()):
        super().__init__()
        _common_action_count(qnets, "a model bank", "a bank")
        self.qnets = nn.ModuleList(qnets)
        self.rule = rule
        self.current = self.steps_on = self.r_start = None

    def _choose(self, r: torch.Tensor, step_count: torch.Tensor) -> torch.Tensor:
        rule, new = self.rule, step_count == 0
        if self.current is None or self.current.shape != r.shape:
            self.current, self.steps_on, self.r_start = torch.zeros_like(step_count), torch.zeros_like(step_count), r.clone()
        self.current = torch.where(new, 0, self.current)
        self.steps_on = torch.where(new, 0, self.steps_on)
        self.r_start = torch.where(new, r, self.r_start)
        locked = r >= rule.lock_r
        trial_over = self.steps_on >= rule.steps
        rose = r >= self.r_start + rule.min_rise
        switch = trial_over & ~rose & ~locked
        self.current = torch.where(switch, (self.current + 1) % len(self.qnets), self.current)
        restart = trial_over | locked  # a new trial (of the same model if r rose or it is locked)
        self.steps_on = torch.where(restart, 0, self.steps_on) + 1
        self.r_start = torch.where(restart, r, self.r_start)
        return self.current

    def forward(self, *obs_r_step: torch.Tensor):
        *obs, r, step_count = obs_r_step
        model = self._choose(r.reshape(r.shape[:-1]).to(torch.float64), step_count.reshape(step_count.shape[:-1]))
        return _q_of(torch.stack([net(*obs) for net in self.qnets]), model), model


def make_trial_actor(qnets: list[QNet], action_spec, rule: TrialRule = TrialRule()) -> TensorDictSequential:
    """Greedy policy of a ``TrialBank``: writes ``action``, ``action_value`` and ``model``. It judges
    the models by the reward their observation gives: r with the fields, r_measured with readings."""
    keys = _in_keys(qnets)
    reward = "r" if "fields" in keys else "r_measured"
    bank = TensorDictModule(TrialBank(qnets, rule), in_keys=[*keys, reward, "step_count"],
                            out_keys=["action_value", "model"])
    return TensorDictSequential(bank, QValueModule(spec=action_spec))


def nearest_model(model_K: Sequence[float | tuple[float, float]], K: float) -> int:
    """Index of the bank model for K: the first model fine-tuned over a K range that holds K;
    otherwise the model whose K (or the centre of whose range) is nearest, ties going to
    the first model in the bank."""
    for j, m in enumerate(model_K):
        if not isinstance(m, (int, float)) and m[0] <= K <= m[1]:
            return j
    centres = [m if isinstance(m, (int, float)) else 0.5 * (m[0] + m[1]) for m in model_K]
    return min(range(len(model_K)), key=lambda j: abs(centres[j] - K))


class NearestKBank(nn.Module):
    """Per cavity, the Q-values of the model trained nearest the cavity's K now (``nearest_model``:
    the oracle rule, told K); and that model's index. ``model_K``: each model's training K (a
    value, or a (low, high) range)."""

    def __init__(self, qnets: list[QNet], model_K: Sequence[float | tuple[float, float]]):
        super().__init__()
        _common_action_count(qnets, "a model bank", "a bank")
        if len(model_K) != len(qnets):
            raise ValueError(f"a bank of {len(qnets)} models needs {len(qnets)} training K values, got {list(model_K)}")
        self.qnets = nn.ModuleList(qnets)
        self.model_K = [k if isinstance(k, (int, float)) else (float(k[0]), float(k[1])) for k in model_K]

    def forward(self, *obs_K: torch.Tensor):
        *obs, K = obs_K
        model = torch.tensor([nearest_model(self.model_K, float(k)) for k in K.reshape(-1)], dtype=torch.int64,
                             device=K.device).reshape(K.shape[:-1])
        return _q_of(torch.stack([net(*obs) for net in self.qnets]), model), model


def make_nearest_actor(qnets: list[QNet], model_K, action_spec) -> TensorDictSequential:
    """Greedy policy of a ``NearestKBank``: reads the observation and ``K``; writes ``action``,
    ``action_value`` and ``model``."""
    bank = TensorDictModule(NearestKBank(qnets, model_K), in_keys=[*_in_keys(qnets), "K"],
                            out_keys=["action_value", "model"])
    return TensorDictSequential(bank, QValueModule(spec=action_spec))
