"""Env factory importable by worker processes (multi-process collectors spawn)."""
from __future__ import annotations

import dataclasses
import numbers
import re
from typing import Any, Mapping

import torch
from torchrl.envs import Compose, TransformedEnv

from laserrl.envs.laser_env import LaserCavityEnv, LaserTask, finite_number, policy_keys
from laserrl.envs.transforms import centred_reward, recurrent_memory, stacked_history
from laserrl.physics import CavityParams

TASK_KEYS = ("controlled", "steps_deg", "init_angles_deg", "K", "K_drift", "K_jump", "init_fields", "sech_amplitude",
             "sech_width", "noise_scale", "max_steps", "move_cost",
             "move_cost_from", "fine_steps_deg", "fine_from")
ENV_TASK_KEYS = ("max_round_trips", "min_round_trips", "tol", "dtype", "compile", "observation",
                 "instruments", "physics_spread")  # LaserTask fields set from the env group
#: (center, scale) of the training reward (r - center) / scale when env.reward_center / reward_scale are null:
#: the paper's for r (a plane wave about -0.8, a mode-locked pulse about +1), and the same for the measured
#: reward, whose mode-locked states lie near 0.55 and plane waves near 0.05 (laserrl.analysis.measured)
REWARD_CENTRING = {"fields": (0.1, 0.1), "measured": (0.3, 0.3)}


def min_round_trips(env_cfg: Mapping[str, Any]) -> int:
    """``env.min_round_trips``; 1 (the paper's rule, which the env ran then) for the saved config
    of a run from before the key existed."""
    return env_cfg.get("min_round_trips", 1)


def make_task(env_cfg: Mapping[str, Any], stage_cfg: Mapping[str, Any], **overrides) -> LaserTask:
    """LaserTask from the ``env`` (numerics) and ``stage`` (what is controlled) config groups;
    a bad value raises a ValueError naming its config key (``stage.K``, ``env.dtype``, ...)."""
    kwargs = {k: stage_cfg[k] for k in TASK_KEYS if k in stage_cfg}  # LaserTask takes lists as ranges
    kwargs.update(max_round_trips=env_cfg["max_round_trips"], min_round_trips=min_round_trips(env_cfg),
                  tol=env_cfg.get("tol"), dtype=env_cfg["dtype"], compile=env_cfg["compile"],
                  observation=env_cfg.get("observation", "fields"), instruments=env_cfg.get("instruments"),
                  physics_spread=env_cfg.get("physics_spread"))
    kwargs.update(overrides)
    try:
        return LaserTask(**kwargs)
    except ValueError as err:  # LaserTask's messages start with the field's name
        field = re.match(r"\w*", str(err)).group()
        raise ValueError(f"{'env' if field in ENV_TASK_KEYS else 'stage'}.{err}") from None


def make_params(env_cfg: Mapping[str, Any]) -> CavityParams:
    """CavityParams from ``env.physics``; a bad value raises a ValueError naming ``env.physics.KEY``."""
    physics = dict(env_cfg.get("physics") or {})
    unknown = set(physics) - {f.name for f in dataclasses.fields(CavityParams)}
    if unknown:
        raise ValueError(f"env.physics: unknown key(s) {sorted(unknown)}")
    try:
        return CavityParams(**physics)
    except ValueError as err:
        raise ValueError(str(err).replace("CavityParams.", "env.physics.", 1)) from None


def history_length(env_cfg: Mapping[str, Any]) -> int:
    """``env.history``: how many observations the agent sees at once (1: the current one)."""
    h = env_cfg.get("history", 1)
    if isinstance(h, bool) or not isinstance(h, numbers.Integral) or h < 1:
        raise ValueError(f"env.history must be a positive integer, got {h!r}")
    return int(h)


def gru_size(env_cfg: Mapping[str, Any]) -> int | None:
    """``env.gru_size``: the size of a GRU agent's hidden state, which the env carries between
    steps (None: a feed-forward agent, the paper's)."""
    size = env_cfg.get("gru_size")
    if size is None:
        return None
    if isinstance(size, bool) or not isinstance(size, numbers.Integral) or size < 1:
        raise ValueError(f"env.gru_size must be null or a positive integer, got {size!r}")
    return int(size)


def reward_centring(env_cfg: Mapping[str, Any]) -> tuple[float, float]:
    """(center, scale) of the training reward: ``env.reward_center`` / ``reward_scale``, null ones by
    ``env.observation`` (``REWARD_CENTRING``)."""
    default = REWARD_CENTRING.get(env_cfg.get("observation", "fields"), REWARD_CENTRING["fields"])
    center, scale = (default[i] if env_cfg.get(key) is None else env_cfg[key]
                     for i, key in enumerate(("reward_center", "reward_scale")))
    center = finite_number(center, "env.reward_center")
    scale = finite_number(scale, "env.reward_scale")
    if not scale > 0:
        raise ValueError(f"env.reward_scale must be > 0, got {scale!r}")
    return center, scale


def make_env(env_cfg: Mapping[str, Any], stage_cfg: Mapping[str, Any], num_envs: int, seed: int,
             device: str = "cpu", centred: bool = True, threads: int | None = None, snapshot: Mapping | None = None,
             **task_overrides):
    """A batched LaserCavityEnv, with the paper's reward centring if ``centred``, the last
    ``env.history`` observations stacked (TorchRL's ``CatFrames``) if more than one, and a GRU
    agent's state carried (``recurrent_memory``) with ``env.gru_size``; with a
    ``snapshot`` (``LaserCavityEnv.snapshot()``) its first reset continues that state."""
    if isinstance(num_envs, bool) or not isinstance(num_envs, numbers.Integral) or num_envs < 1:
        raise ValueError(f"env.num_envs must be a positive integer, got {num_envs!r}")
    if threads:
        torch.set_num_threads(int(threads))
    history, memory = history_length(env_cfg), gru_size(env_cfg)
    centring = reward_centring(env_cfg) if centred else None
    task, params = make_task(env_cfg, stage_cfg, **task_overrides), make_params(env_cfg)
    try:
        env = LaserCavityEnv(num_envs, task=task, params=params, device=device, seed=seed)
    except ValueError as err:  # the instruments against the grid
        raise ValueError(f"env.{err}" if str(err).startswith("instruments.") else str(err)) from None
    if snapshot is not None:
        env.continue_from(snapshot)
    transforms = []
    if history > 1:
        transforms.append(stacked_history(history, policy_keys(env.task)))
    if centring is not None:
        transforms.append(centred_reward(*centring))
    if memory is not None:
        transforms += recurrent_memory(memory)
    return TransformedEnv(env, Compose(*transforms)) if transforms else env
