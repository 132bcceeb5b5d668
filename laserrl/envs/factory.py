"""Env factory importable by worker processes (multi-process collectors spawn)."""
from __future__ import annotations

from typing import Any, Mapping

import torch
from torchrl.envs import TransformedEnv

from laserrl.envs.laser_env import LaserCavityEnv, LaserTask
from laserrl.envs.transforms import centred_reward
from laserrl.physics import CavityParams

TASK_KEYS = ("controlled", "steps_deg", "init_angles_deg", "K", "init_fields", "sech_amplitude", "sech_width",
             "noise_scale", "max_steps")


def make_task(env_cfg: Mapping[str, Any], stage_cfg: Mapping[str, Any], **overrides) -> LaserTask:
    """LaserTask from the ``env`` (numerics) and ``stage`` (what is controlled) config groups."""
    kwargs = {k: stage_cfg[k] for k in TASK_KEYS if k in stage_cfg}  # LaserTask takes lists as ranges
    kwargs.update(max_round_trips=env_cfg["max_round_trips"], tol=env_cfg.get("tol"), dtype=env_cfg["dtype"],
                  compile=env_cfg["compile"])
    kwargs.update(overrides)
    return LaserTask(**kwargs)


def make_params(env_cfg: Mapping[str, Any]) -> CavityParams:
    return CavityParams(**dict(env_cfg.get("physics", {})))


def make_env(env_cfg: Mapping[str, Any], stage_cfg: Mapping[str, Any], num_envs: int, seed: int,
             device: str = "cpu", centred: bool = True, threads: int | None = None, **task_overrides):
    """A batched LaserCavityEnv, with the paper's reward centring if ``centred``."""
    if threads:
        torch.set_num_threads(int(threads))
    env = LaserCavityEnv(num_envs, task=make_task(env_cfg, stage_cfg, **task_overrides), params=make_params(env_cfg),
                         device=device, seed=seed)
    if centred:
        env = TransformedEnv(env, centred_reward(env_cfg["reward_center"], env_cfg["reward_scale"]))
    return env
