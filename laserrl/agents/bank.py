"""A bank of Q-networks trained at different birefringence K, acting as one policy.

K is not observed, so a bank cannot simply pick the model trained nearest the true K.
``MaxQBank`` picks, for every cavity at every step, the model whose greedy Q-value is
highest (each model's estimate of the return it can still collect) and acts with that
model's greedy action. The oracle rule that knows K (nearest training K) is an
evaluation-side grouping, see ``laserrl.evaluate.evaluate_bank``.

A bank member can itself be an ensemble, ``MeanQ``: several Q-networks trained for the same
task (for example the seeds of one fine-tuning recipe) whose Q-values are averaged. Where the
greedy choice hangs on Q-value differences of a few percent (a lock one angle wide), the
seeds' errors in those differences are partly independent, and their mean picks more
reliably than any one of them.
"""
from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import QValueModule

from laserrl.agents.qnet import FieldQNet
from laserrl.agents.dqn import OBS_KEYS

__all__ = ["MaxQBank", "MeanQ", "make_bank_actor"]


def _common_action_count(qnets: list[nn.Module], group: str, of_group: str) -> int:
    """The number of actions that all ``qnets`` share; ValueError if there are none or they differ.
    ``group`` / ``of_group`` name the collection in the messages ("a model bank" / "a bank")."""
    if not qnets:
        raise ValueError(f"{group} needs at least one Q-network")
    actions = {q.num_actions for q in qnets}
    if len(actions) != 1:
        raise ValueError(f"all models of {of_group} must have the same number of actions, got {sorted(actions)}")
    return actions.pop()


class MeanQ(nn.Module):
    """The mean of the Q-values of several Q-networks with the same actions (an ensemble)."""

    def __init__(self, qnets: list[nn.Module]):
        super().__init__()
        self.num_actions = _common_action_count(qnets, "an ensemble", "an ensemble")
        self.qnets = nn.ModuleList(qnets)

    def forward(self, fields: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
        return torch.stack([net(fields, angles) for net in self.qnets]).mean(0)


class MaxQBank(nn.Module):
    """Q-values of the model with the highest max Q, per cavity; and that model's index."""

    def __init__(self, qnets: list[FieldQNet | MeanQ]):
        super().__init__()
        _common_action_count(qnets, "a model bank", "a bank")
        self.qnets = nn.ModuleList(qnets)

    def forward(self, fields: torch.Tensor, angles: torch.Tensor):
        q = torch.stack([net(fields, angles) for net in self.qnets])  # (M, *batch, A)
        model = q.max(-1).values.argmax(0)  # (*batch,)
        chosen = torch.gather(q, 0, model[None, ..., None].expand(1, *q.shape[1:]))[0]
        return chosen, model


def make_bank_actor(qnets: list[FieldQNet | MeanQ], action_spec) -> TensorDictSequential:
    """Greedy policy of a ``MaxQBank``: writes ``action``, ``action_value`` and ``model``."""
    bank = TensorDictModule(MaxQBank(qnets), in_keys=OBS_KEYS, out_keys=["action_value", "model"])
    return TensorDictSequential(bank, QValueModule(spec=action_spec))
