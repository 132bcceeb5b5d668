"""Gymnasium entry points of the laser cavity.

``import laserrl`` registers one id per task of the Hydra configs (``laserrl/conf/stage``)::

    laserrl/ModeLock-SISO-v0   alpha1 in 2 deg steps (3 actions), 20 steps per episode
    laserrl/ModeLock-Duo-v0    alpha1, alpha2 in 2 deg steps (9 actions), 40 steps
    laserrl/ModeLock-MISO-v0   all four angles in 0.5 deg steps (81 actions), 100 steps

each with the numerics and physics of ``conf/env/paper.yaml``, and a ``-PaperExact-v0``
twin of each (``laserrl/ModeLock-SISO-PaperExact-v0``, ...) with those of
``experiment=paper_exact``: the paper's stopping rule (at least one round trip, then until
converged to 1e-6, at most 500) in complex128. The settings are read from the package's
YAML files when an env is made, so an id always runs what ``laserrl-train`` runs, except
that ``compile`` is off by default: ``compile=True`` costs 20-40 s before the first step,
then each step runs several times faster (worth it for long runs).

    >>> import gymnasium, laserrl
    >>> env = gymnasium.make("laserrl/ModeLock-SISO-v0")
    >>> obs, info = env.reset(seed=0)
    >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

Observation: ``Dict(fields=Box(-inf, inf, (4, n)), angles=Box(-pi/2, pi/2, (4,)))``, float32:
the fields (Re u, Im u, Re v, Im v) on the n = 256 time samples and the four plate angles
(alpha1, alpha2, alpha3, alpha_p) in radians; with ``observation="measured"`` the instruments'
readings ``spectrum``, ``energy`` and ``autocorrelation`` (``laserrl.physics.instruments``)
instead of the fields. The birefringence K is not observed.
Action: ``Discrete(3**m)`` for m controlled angles (``laserrl.envs.actions``: digit j of the
action in base 3 turns angle j down, holds it, or turns it up by its step).
Reward: the training reward (r - reward_center) / reward_scale of ``laserrl-train``;
``info["r"]`` is the raw r = E / M4 and ``info["round_trips"]`` the round trips the step ran.
Episodes never terminate; they are truncated after the task's ``max_steps`` steps.

Keyword arguments of ``gymnasium.make`` (and ``make_vec``) change the settings:

- any key of the ``env`` config: ``max_round_trips``, ``min_round_trips``, ``tol``,
  ``dtype`` ("complex64" or "complex128"), ``compile``, ``reward_center``, ``reward_scale``,
  ``physics`` (a dict of ``CavityParams`` fields, e.g. ``physics={"n": 128}``), ``observation``
  ("fields" or "measured"), ``instruments`` (a dict of their settings);
- any key of the task: ``K`` (a number or a [low, high] range sampled at reset),
  ``init_angles_deg`` (a dict of angles, each a number or a [low, high] range; the angles
  it leaves out keep the task's),
  ``init_fields`` ("sech" or "noise"), ``max_steps``, ``controlled``, ``steps_deg``,
  ``sech_amplitude``, ``sech_width``, ``noise_scale``;
- ``device`` ("cpu", "cuda") and ``threads`` (torch's intra-op threads; None leaves them).

A bad keyword or value raises one ``laserrl.validate.ConfigError`` (a ValueError) naming it.
``reset(options=...)`` takes ``{"angles_deg": [a1, a2, a3, ap], "K": k}`` to start from
given angles (degrees) or birefringence instead of sampled ones.

``gymnasium.make_vec(id, num_envs=N)`` steps N cavities in one batched ``LaserCavityEnv``
(``ModeLockVectorEnv``), not N copies; it resets a cavity whose episode ended on the next
step (``AutoresetMode.NEXT_STEP``, gymnasium's default; ``autoreset_mode="SameStep"`` or
``"Disabled"`` choose otherwise).
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Mapping

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from laserrl.paths import CONF_DIR
from laserrl.validate import ConfigError

__all__ = ["ENV_IDS", "ModeLockEnv", "ModeLockVectorEnv", "load_configs", "register_envs"]

#: The registered ids and the (stage, experiment) configs each one runs.
ENV_IDS = {
    f"laserrl/ModeLock-{label}{suffix}-v0": (stage, experiment)
    for label, stage in (("SISO", "siso"), ("Duo", "duo"), ("MISO", "miso"))
    for suffix, experiment in (("", None), ("-PaperExact", "paper_exact"))
}
_MAPPING_KEYS = ("physics", "init_angles_deg", "instruments")  # merged into the config's mapping, not replacing it
_OWN_KEYS = ("device", "threads")


def register_envs() -> None:
    """Register ``ENV_IDS`` with gymnasium (done by ``import laserrl``; ids already there are kept)."""
    for env_id, (stage, experiment) in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point="laserrl.gym:ModeLockEnv",
                               vector_entry_point="laserrl.gym:ModeLockVectorEnv",
                               kwargs={"stage": stage, "experiment": experiment})


def load_configs(stage: str = "siso", experiment: str | None = None) -> tuple[dict, dict]:
    """The ``env`` and ``stage`` config groups of ``laserrl-train stage=STAGE experiment=EXPERIMENT``,
    as plain dicts (only the ``env`` group of the experiment is applied)."""
    from omegaconf import OmegaConf

    conf = Path(CONF_DIR)
    stages = sorted(p.stem for p in (conf / "stage").glob("*.yaml"))
    if stage not in stages:
        raise ConfigError(f"stage must be one of {', '.join(stages)}, got {stage!r}")
    experiments = sorted(p.stem for p in (conf / "experiment").glob("*.yaml"))
    if experiment is not None and experiment not in experiments:
        raise ConfigError(f"experiment must be None or one of {', '.join(experiments)}, got {experiment!r}")
    env_cfg = OmegaConf.load(conf / "env" / "paper.yaml")
    if experiment is not None:
        env_cfg = OmegaConf.merge(env_cfg, OmegaConf.load(conf / "experiment" / f"{experiment}.yaml").get("env", {}))
    stage_file = conf / "stage" / f"{stage}.yaml"
    return OmegaConf.to_container(env_cfg, resolve=True), OmegaConf.to_container(OmegaConf.load(stage_file))


def _configs_with(stage: str, experiment: str | None, overrides: Mapping[str, Any]) -> tuple[dict, dict]:
    """``load_configs`` with the keyword arguments of ``gymnasium.make`` applied."""
    from laserrl.envs.factory import TASK_KEYS

    env_cfg, stage_cfg = load_configs(stage, experiment)
    env_cfg.pop("num_envs", None)  # the batch is the vector env's num_envs (1 for gymnasium.make)
    env_cfg["compile"] = False
    env_keys, stage_keys = set(env_cfg), set(TASK_KEYS)
    unknown = set(overrides) - env_keys - stage_keys - set(_OWN_KEYS)
    if unknown:
        known = sorted(env_keys | stage_keys | set(_OWN_KEYS))
        raise ConfigError(f"unknown keyword argument(s) {sorted(unknown)} for the laserrl/ModeLock envs; "
                          f"choose from {known}")
    for key, value in overrides.items():
        if key in _OWN_KEYS:
            continue
        cfg = env_cfg if key in env_keys else stage_cfg
        if key in _MAPPING_KEYS:
            if not isinstance(value, Mapping):
                raise ConfigError(f"{key} must be a dict, got {value!r}")
            value = {**cfg.get(key, {}), **value}
        if key == "compile" and not isinstance(value, bool):
            raise ConfigError(f"compile must be True or False, got {value!r}")
        if key == "dtype" and not isinstance(value, str):
            value = str(value).removeprefix("torch.")  # torch.complex128 -> "complex128"
        cfg[key] = value
    return env_cfg, stage_cfg


class _Cavities:
    """The training env of N cavities (``laserrl.envs.factory.make_env``) with numpy in and out;
    both gymnasium classes below are views of it."""

    def __init__(self, num_envs, stage: str, experiment: str | None, overrides: Mapping[str, Any]):
        # torch and TorchRL load here, not at import: ``import laserrl`` registers the ids, and
        # should stay light and keep TorchRL out of programs that use only the physics
        from laserrl.config import check_device
        from laserrl.envs.factory import gru_size, history_length, make_env
        from laserrl.envs.laser_env import policy_keys

        env_cfg, stage_cfg = _configs_with(stage, experiment, overrides)
        device = overrides.get("device", "cpu")
        check_device(device)
        threads = overrides.get("threads")
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
            raise ConfigError(f"threads must be None or a positive integer, got {threads!r}")
        try:
            self.env = make_env(env_cfg, stage_cfg, num_envs, seed=None, device=device, threads=threads)
        except ValueError as err:  # messages start with the config key: name it as the keyword is spelt
            raise ConfigError(re.sub(r"^(env|stage)\.", "", str(err))) from None
        if history_length(env_cfg) != 1:  # reset below steps the base env, past a history transform
            raise ConfigError("history: the Gymnasium envs give one observation per step; stack them with "
                              "gymnasium.wrappers.FrameStackObservation")
        if gru_size(env_cfg) is not None:
            raise ConfigError("gru_size: the Gymnasium envs give observations only; a recurrent agent keeps its own state")
        base = self.env.base_env
        self.num_envs = base.batch_size[0]
        self.device = base.device
        self.keys = policy_keys(base.task)
        spec = base.observation_spec
        self.single_observation_space = spaces.Dict({
            key: (spaces.Box(-math.pi / 2, math.pi / 2, shape=(4,), dtype=np.float32) if key == "angles" else
                  spaces.Box(-np.inf, np.inf, shape=tuple(spec[key].shape[1:]), dtype=np.float32))
            for key in self.keys})
        self.single_action_space = spaces.Discrete(base.task.num_actions)

    def reset(self, seed: int | None = None, options: Mapping | None = None, mask: np.ndarray | None = None):
        """Observation and info of all cavities after resetting those in ``mask`` (all: None)."""
        import torch
        from tensordict import TensorDict

        if seed is not None:
            self.env.set_seed(int(seed))
        request = TensorDict({}, batch_size=[self.num_envs], device=self.device)
        options = dict(options or {})
        unknown = set(options) - {"angles_deg", "K"}
        if unknown:
            raise ValueError(f"reset options: unknown key(s) {sorted(unknown)}; give angles_deg and/or K")
        if "angles_deg" in options:
            angles = torch.as_tensor(np.asarray(options["angles_deg"], dtype=np.float64), device=self.device)
            if angles.shape[-1:] != (4,) or angles.ndim > 2:
                raise ValueError(f"reset options: angles_deg must be the four angles (alpha1, alpha2, alpha3, "
                                 f"alpha_p) in degrees, got shape {tuple(angles.shape)}")
            request["init_angles"] = torch.deg2rad(angles).expand(self.num_envs, 4).clone()
        if "K" in options:
            K = torch.as_tensor(np.asarray(options["K"], dtype=np.float64), device=self.device)
            request["init_K"] = K.expand(self.num_envs).clone()
        if mask is not None:
            request["_reset"] = torch.as_tensor(mask, device=self.device).reshape(self.num_envs, 1)
        # the base env: TransformedEnv.reset passes on only the state keys of its input, which
        # would drop init_angles and init_K; the reward transform has nothing to reset
        out = self.env.base_env.reset(request)
        return self._observation(out), self._info(out)

    def step(self, actions: np.ndarray):
        """Observation, training reward, truncation and info of all cavities after ``actions`` (N,)."""
        import torch
        from tensordict import TensorDict

        actions = np.asarray(actions)
        n = self.single_action_space.n
        if actions.shape != (self.num_envs,) or not np.issubdtype(actions.dtype, np.integer) \
                or actions.min() < 0 or actions.max() >= n:
            raise ValueError(f"actions must be {self.num_envs} integer(s) in [0, {n}), got {actions!r}")
        request = TensorDict({"action": torch.as_tensor(actions, dtype=torch.int64, device=self.device)},
                             batch_size=[self.num_envs], device=self.device)
        out = self.env.step(request)["next"]
        reward = out["reward"].reshape(-1).cpu().numpy().astype(np.float64)
        truncated = out["truncated"].reshape(-1).cpu().numpy().copy()
        return self._observation(out), reward, truncated, self._info(out)

    def _observation(self, td) -> dict[str, np.ndarray]:
        return {key: td[key].cpu().numpy().copy() for key in self.keys}

    @staticmethod
    def _info(td) -> dict[str, np.ndarray]:
        return {"r": td["r"].reshape(-1).cpu().numpy().copy(),
                "round_trips": td["round_trips"].reshape(-1).cpu().numpy().copy()}


def _check_render_mode(render_mode) -> None:
    if render_mode is not None:
        raise ConfigError(f"render_mode: the laserrl/ModeLock envs do not render, got {render_mode!r}")


class ModeLockEnv(gymnasium.Env):
    """One laser cavity as a ``gymnasium.Env`` (see the module docstring for the spaces and
    keyword arguments). ``torchrl_env`` is the TorchRL env underneath (a batch of one cavity),
    e.g. for ``torchrl_env.base_env.set_K(...)`` to make K drift."""

    metadata = {"render_modes": []}

    def __init__(self, stage: str = "siso", experiment: str | None = None, render_mode: str | None = None,
                 **kwargs):
        _check_render_mode(render_mode)
        self._cavities = _Cavities(1, stage, experiment, kwargs)
        self.torchrl_env = self._cavities.env
        self.observation_space = self._cavities.single_observation_space
        self.action_space = self._cavities.single_action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, info = self._cavities.reset(seed=seed, options=options)
        return _first(obs), _first(info)

    def step(self, action):
        obs, reward, truncated, info = self._cavities.step(np.asarray(action).reshape(1))
        return _first(obs), float(reward[0]), False, bool(truncated[0]), _first(info)


def _first(batch: dict[str, np.ndarray]) -> dict:
    """The first cavity of a batch: arrays for observations, Python numbers for info."""
    return {k: (v[0] if v.ndim > 1 else v[0].item()) for k, v in batch.items()}


class ModeLockVectorEnv(VectorEnv):
    """``num_envs`` laser cavities stepped together in one batched TorchRL env, as a
    ``gymnasium.vector.VectorEnv`` (``gymnasium.make_vec``).

    Autoreset follows ``autoreset_mode`` (``metadata["autoreset_mode"]``):

    - ``NEXT_STEP`` (default): the step after an episode ended resets that cavity, ignores its
      action and returns its first observation with reward 0;
    - ``SAME_STEP``: the step that ends an episode returns the next episode's first observation;
      the last one is in ``info["final_obs"]`` (and its info in ``info["final_info"]``);
    - ``DISABLED``: reset ended cavities yourself, ``reset(options={"reset_mask": mask})``.

    ``reset(seed=s)`` seeds the one generator of the batch, so ``seed`` is one int (not one per
    cavity). Infos are arrays over the cavities, each key with its ``_key`` mask.
    """

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, stage: str = "siso", experiment: str | None = None,
                 render_mode: str | None = None, autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
                 **kwargs):
        _check_render_mode(render_mode)
        try:
            autoreset_mode = AutoresetMode(autoreset_mode)
        except ValueError:
            raise ConfigError(f"autoreset_mode must be one of {[m.value for m in AutoresetMode]}, "
                              f"got {autoreset_mode!r}") from None
        self._cavities = _Cavities(num_envs, stage, experiment, kwargs)
        self.torchrl_env = self._cavities.env
        self.num_envs = self._cavities.num_envs
        self.metadata = {**type(self).metadata, "autoreset_mode": autoreset_mode}
        self.single_observation_space = self._cavities.single_observation_space
        self.single_action_space = self._cavities.single_action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._ended = np.zeros(self.num_envs, dtype=bool)  # episodes that ended on the last step

    @property
    def autoreset_mode(self) -> AutoresetMode:
        return self.metadata["autoreset_mode"]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset all cavities, or those in ``options["reset_mask"]`` (a bool array (num_envs,))."""
        if seed is not None and not isinstance(seed, (int, np.integer)):
            raise ValueError(f"seed must be one int for the batch of cavities (one generator), got {seed!r}")
        seed = None if seed is None else int(seed)
        super().reset(seed=seed)
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != (self.num_envs,) or mask.dtype != np.bool_ or not mask.any():
                raise ValueError(f"options['reset_mask'] must be a bool array of shape ({self.num_envs},) "
                                 f"with at least one True, got {mask!r}")
        obs, info = self._cavities.reset(seed=seed, options=options, mask=mask)
        self._ended = np.zeros_like(self._ended) if mask is None else self._ended & ~mask
        return obs, _with_masks(info, self.num_envs)

    def step(self, actions):
        restart = self._ended.copy()
        terminated = np.zeros(self.num_envs, dtype=bool)
        if self.autoreset_mode == AutoresetMode.DISABLED and restart.any():
            raise RuntimeError(f"cavities {np.flatnonzero(restart).tolist()} ended their episode: reset them "
                               "with reset(options={'reset_mask': mask}) before the next step (autoreset disabled)")
        if self.autoreset_mode == AutoresetMode.NEXT_STEP and restart.all():
            # every episode ended together (the usual case: they all last max_steps): only reset
            obs, info = self._cavities.reset()
            reward, truncated = np.zeros(self.num_envs), np.zeros(self.num_envs, dtype=bool)
        elif self.autoreset_mode == AutoresetMode.NEXT_STEP and restart.any():
            # the batch steps together; the restarting cavities' step is then replaced by their reset
            _, reward, truncated, stepped_info = self._cavities.step(actions)
            obs, info = self._cavities.reset(mask=restart)
            reward[restart], truncated[restart] = 0.0, False
            info = {k: np.where(restart, v, stepped_info[k]) for k, v in info.items()}
        else:
            obs, reward, truncated, info = self._cavities.step(actions)
        self._ended = terminated | truncated
        info = _with_masks(info, self.num_envs)
        if self.autoreset_mode == AutoresetMode.SAME_STEP and self._ended.any():
            ended = self._ended
            final_obs = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(ended):
                final_obs[i] = {k: v[i].copy() for k, v in obs.items()}
            final_info = {k: (ended.copy() if k.startswith("_") else v) for k, v in info.items()}
            obs, reset_info = self._cavities.reset(mask=ended)
            info = {k: np.where(ended, v, info[k]) for k, v in reset_info.items()}
            info = {**_with_masks(info, self.num_envs), "final_obs": final_obs, "_final_obs": ended.copy(),
                    "final_info": final_info, "_final_info": ended.copy()}
            self._ended = np.zeros_like(ended)
        return obs, reward, terminated, truncated, info


def _with_masks(info: dict[str, np.ndarray], num_envs: int) -> dict:
    """Vector info: each key with its ``_key`` mask (every cavity reports every key)."""
    out = {}
    for key, value in info.items():
        out[key] = value
        out[f"_{key}"] = np.ones(num_envs, dtype=bool)
    return out


register_envs()
