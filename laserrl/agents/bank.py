"""A bank of Q-networks trained at different birefringence K, acting as one policy.

K is not observed, so a bank cannot simply pick the model trained nearest the true K.
``MaxQBank`` picks, for every cavity at every step, the model whose greedy Q-value is
highest (each model's estimate of the return it can still collect) and acts with that
model's greedy action. The oracle rule that knows K (nearest training K) is an
evaluation-side grouping, see ``laserrl.evaluate.evaluate_bank``.
"""
from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import QValueModule

from laserrl.agents.qnet import FieldQNet
from laserrl.agents.dqn import OBS_KEYS

__all__ = ["MaxQBank", "make_bank_actor"]


class MaxQBank(nn.Module):
    """Q-values of the model with the highest max Q, per cavity; and that model's index."""

    def __init__(self, qnets: list[FieldQNet]):
        super().__init__()
        if not qnets:
            raise ValueError("a model bank needs at least one Q-network")
        actions = {q.num_actions for q in qnets}
        if len(actions) != 1:
            raise ValueError(f"all models of a bank must have the same number of actions, got {sorted(actions)}")
        self.qnets = nn.ModuleList(qnets)

    def forward(self, fields: torch.Tensor, angles: torch.Tensor):
        q = torch.stack([net(fields, angles) for net in self.qnets])  # (M, *batch, A)
        model = q.max(-1).values.argmax(0)  # (*batch,)
        chosen = torch.gather(q, 0, model[None, ..., None].expand(1, *q.shape[1:]))[0]
        return chosen, model


def make_bank_actor(qnets: list[FieldQNet], action_spec) -> TensorDictSequential:
    """Greedy policy of a ``MaxQBank``: writes ``action``, ``action_value`` and ``model``."""
    bank = TensorDictModule(MaxQBank(qnets), in_keys=OBS_KEYS, out_keys=["action_value", "model"])
    return TensorDictSequential(bank, QValueModule(spec=action_spec))
