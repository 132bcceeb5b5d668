"""Warm-starting a Q-network from a checkpoint, across stages of the curriculum.

Every stage sees the same observation (the four fields and all four angles), so every
layer keeps its shape except the Q-head, which has 3^m outputs for m controlled angles.

Rule for a grown head: a new joint action inherits the Q-value row (weights and bias of
the last layer) of the old joint action that moves the *old* controlled angles the same
way. E.g. from ``siso`` (alpha1) to ``duo`` (alpha1, alpha2): the new actions
"alpha1 up, alpha2 down/hold/up" all start from the old "alpha1 up". The new angles'
moves therefore start indifferent, and the learned alpha1 behaviour carries over.

The same for an additive head (``agent.network.head=additive``; ``laserrl.agents.qnet.AdditiveActionValues``),
whose last layer has a row for V and three per controlled angle: V and each old angle's rows carry
over to the same angle, and the new angles' rows start at zero (their moves indifferent).
"""
from __future__ import annotations

from typing import Sequence

import torch

from laserrl.agents.qnet import AdditiveActionValues, FieldQNet, saved_head
from laserrl.checkpoint import CheckpointError
from laserrl.model import load_model

__all__ = ["warm_start", "head_mapping", "additive_head_mapping"]


def _check_grows(old_controlled: Sequence[str], new_controlled: Sequence[str]) -> None:
    """A head grows only onto a stage that controls every angle the checkpoint controlled."""
    missing = [a for a in old_controlled if a not in new_controlled]
    if missing:
        raise CheckpointError(f"cannot grow the Q-head: the checkpoint controls {list(old_controlled)}, "
                              f"this stage controls {list(new_controlled)} (missing {missing})")


def head_mapping(old_controlled: Sequence[str], new_controlled: Sequence[str]) -> torch.Tensor:
    """For every new joint action, the index of the old joint action it inherits from.

    Actions use ``laserrl.envs.action_to_deltas``'s encoding (base 3, first controlled
    angle least significant). Requires the old angles to be a subset of the new ones.
    """
    _check_grows(old_controlled, new_controlled)
    m_new = len(new_controlled)
    new_actions = torch.arange(3**m_new)
    digits = torch.stack([(new_actions // 3**j) % 3 for j in range(m_new)], -1)  # (A_new, m_new)
    old = torch.zeros_like(new_actions)
    for i, name in enumerate(old_controlled):
        old += digits[:, list(new_controlled).index(name)] * 3**i
    return old


def additive_head_mapping(old_controlled: Sequence[str], new_controlled: Sequence[str]) -> torch.Tensor:
    """For every row of a grown additive head's last layer (V, then down / hold / up of each new
    controlled angle), the old row it inherits, or -1 for the moves of an angle the old head lacks."""
    _check_grows(old_controlled, new_controlled)
    rows = [0]
    for name in new_controlled:
        i = list(old_controlled).index(name) if name in old_controlled else None
        rows += [-1, -1, -1] if i is None else [1 + 3 * i + d for d in range(3)]
    return torch.tensor(rows)


def head_kind(qnet) -> str:
    """``additive`` if ``qnet`` ends in ``AdditiveActionValues``, else ``joint``."""
    return "additive" if isinstance(qnet.head[-1], AdditiveActionValues) else "joint"


def warm_start(qnet: FieldQNet, checkpoint: str, controlled: Sequence[str] | None = None) -> dict:
    """Copy a checkpoint's Q-network into ``qnet``; grow the head by ``head_mapping`` if needed.

    Args:
        qnet: the new network (its head may be larger than the checkpoint's).
        checkpoint: a model (``laserrl.model.model_dir``: zoo:NAME, a model or run directory).
        controlled: the angles the new stage controls (needed only when the head grows).
    """
    state = load_model(checkpoint)
    if state["meta"].get("ensemble", 1) != 1:
        raise CheckpointError(f"{state['path']} is an ensemble of {state['meta']['ensemble']} models; warm-start "
                              "from one of its members")
    weights = dict(state["qnet"])
    old_head, new_head = saved_head(state["config"]), head_kind(qnet)
    if old_head != new_head:
        raise CheckpointError(f"checkpoint {state['path']} has a {old_head} Q-head (agent.network.head); "
                              f"this network's is {new_head}")
    old_n, new_n = int(state["num_actions"]), qnet.num_actions
    old_controlled = list(state["config"].get("stage", {}).get("controlled", []))
    refuse = CheckpointError(
        f"checkpoint {state['path']} has a {old_n}-action head for {old_controlled or 'unknown angles'} "
        f"(stage {state.get('stage')}); this task needs {new_n} actions"
        + (f" for {list(controlled)}" if controlled is not None else "")
    )
    if controlled is not None and old_controlled and old_controlled != list(controlled):
        if not set(old_controlled) < set(controlled):
            raise refuse
    elif old_n != new_n:
        raise refuse
    if old_n != new_n:
        last = max(int(k.split(".")[1]) for k in weights if k.startswith("head."))
        if new_head == "joint":
            index = head_mapping(old_controlled, list(controlled))
            for suffix in ("weight", "bias"):
                key = f"head.{last}.{suffix}"
                weights[key] = weights[key][index]
        else:
            index = additive_head_mapping(old_controlled, list(controlled))
            kept = index >= 0
            for suffix in ("weight", "bias"):
                key = f"head.{last}.{suffix}"
                grown = weights[key].new_zeros((len(index), *weights[key].shape[1:]))
                grown[kept] = weights[key][index[kept]]
                weights[key] = grown
    try:
        qnet.load_state_dict(weights)
    except RuntimeError as err:
        raise CheckpointError(f"checkpoint {state['path']} does not match this network: {str(err).splitlines()[0]}") from None
    return state
