"""Transforms used around the laser env."""
from __future__ import annotations

from typing import Sequence

from torchrl.envs.transforms import CatFrames, RewardScaling


def centred_reward(center: float = 0.1, scale: float = 0.1) -> RewardScaling:
    """Training reward (r - center) / scale, as in the paper (reward centred around zero).

    The raw r stays available under the ``r`` key; evaluation reports raw r.
    With the defaults, a plane wave (r < 0.02) gives about -0.8 and a mode-locked
    pulse (r ~ 0.2) about +1.
    """
    return RewardScaling(loc=center, scale=scale, standard_normal=True)


def stacked_history(length: int, keys: Sequence[str]) -> CatFrames:
    """The last ``length`` observations of each of ``keys``, concatenated along the last axis
    (oldest first); a (partial) reset fills a cavity's history with its first observation."""
    return CatFrames(N=int(length), dim=-1, in_keys=list(keys), padding="same")


def recurrent_memory(size: int) -> list:
    """What an env carries for a GRU agent with a hidden state of ``size``: TorchRL's
    ``InitTracker`` (``is_init``: the first step of an episode, where the GRU starts afresh) and
    the ``GRUModule``'s primer (``recurrent_state``, zeros at a reset, carried from step to step)."""
    from torchrl.envs.transforms import InitTracker

    from laserrl.agents.qnet import gru_core

    return [InitTracker(), gru_core(1, size).make_tensordict_primer()]  # the primer depends on the state's size only
