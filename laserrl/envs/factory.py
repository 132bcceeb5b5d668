"""Env factory importable by worker processes (multi-process collectors spawn)."""
from __future__ import annotations

import dataclasses
import numbers
import re
from typing import Any, Mapping

import torch
from torchrl.envs import TransformedEnv

from laserrl.envs.laser_env import LaserCavityEnv, LaserTask, finite_number
from laserrl.envs.transforms import centred_reward
from laserrl.physics import CavityParams

TASK_KEYS = ("controlled", "steps_deg", "init_angles_deg", "K", "init_fields", "sech_amplitude", "sech_width",
             "noise_scale", "max_steps", "move_cost")
ENV_TASK_KEYS = ("max_round_trips", "min_round_trips", "tol", "dtype", "compile")  # LaserTask fields set from the env group


def min_round_trips(env_cfg: Mapping[str, Any]) -> int:
    """``env.min_round_trips``; 1 (the paper's rule, which the env ran then) for the saved config
    of a run from before the key existed."""
    return env_cfg.get("min_round_trips", 1)


def make_task(env_cfg: Mapping[str, Any], stage_cfg: Mapping[str, Any], **overrides) -> LaserTask:
    """LaserTask from the ``env`` (numerics) and ``stage`` (what is controlled) config groups;
    a bad value raises a ValueError naming its config key (``stage.K``, ``env.dtype``, ...)."""
    kwargs = {k: stage_cfg[k] for k in TASK_KEYS if k in stage_cfg}  # LaserTask takes lists as ranges
    kwargs.update(max_round_trips=env_cfg["max_round_trips"], min_round_trips=min_round_trips(env_cfg),
                  tol=env_cfg.get("tol"), dtype=env_cfg["dtype"], compile=env_cfg["compile"])
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


def make_env(env_cfg: Mapping[str, Any], stage_cfg: Mapping[str, Any], num_envs: int, seed: int,
             device: str = "cpu", centred: bool = True, threads: int | None = None, snapshot: Mapping | None = None,
             **task_overrides):
    """A batched LaserCavityEnv, with the paper's reward centring if ``centred``; with a
    ``snapshot`` (``LaserCavityEnv.snapshot()``) its first reset continues that state."""
    if isinstance(num_envs, bool) or not isinstance(num_envs, numbers.Integral) or num_envs < 1:
        raise ValueError(f"env.num_envs must be a positive integer, got {num_envs!r}")
    if threads:
        torch.set_num_threads(int(threads))
    env = LaserCavityEnv(num_envs, task=make_task(env_cfg, stage_cfg, **task_overrides), params=make_params(env_cfg),
                         device=device, seed=seed)
    if snapshot is not None:
        env.continue_from(snapshot)
    if centred:
        center = finite_number(env_cfg["reward_center"], "env.reward_center")
        scale = finite_number(env_cfg["reward_scale"], "env.reward_scale")
        if not scale > 0:
            raise ValueError(f"env.reward_scale must be > 0, got {scale!r}")
        env = TransformedEnv(env, centred_reward(center, scale))
    return env
