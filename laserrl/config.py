"""Config checks, loggers, and turning user errors into one clear line."""
from __future__ import annotations

import contextlib
import math
import shutil
import sys
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from laserrl.checkpoint import CheckpointError


class ConfigError(ValueError):
    """A config value is out of range or of the wrong type."""


@contextlib.contextmanager
def user_errors(prog: str):
    """Report errors caused by the user's input as one line on stderr and exit 2."""
    from laserrl.physics import NonFiniteFieldError

    try:
        yield
    except (ConfigError, CheckpointError, FileNotFoundError, NonFiniteFieldError, OmegaConfBaseException) as err:
        print(f"{prog}: error: {err}".splitlines()[0], file=sys.stderr)
        sys.exit(2)
    except ValueError as err:  # raised by validating constructors (CavityParams, LaserTask, ...)
        print(f"{prog}: error: {err}".splitlines()[0], file=sys.stderr)
        sys.exit(2)


def _number(cfg: DictConfig, dotted: str, *, low=None, high=None, integer=False, low_open=False, optional=False):
    value = OmegaConf.select(cfg, dotted)
    if optional and value is None:
        return
    _check_number(value, dotted, low=low, high=high, integer=integer, low_open=low_open)


def _check_number(value, dotted: str, *, low=None, high=None, integer=False, low_open=False):
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{dotted} must be {kind}, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):  # before int(), which raises its own error on inf, NaN
        raise ConfigError(f"{dotted} must be finite, got {value!r}")
    if integer and int(value) != value:
        raise ConfigError(f"{dotted} must be {kind}, got {value!r}")
    if low is not None and (value <= low if low_open else value < low):
        raise ConfigError(f"{dotted} must be {'>' if low_open else '>='} {low}, got {value!r}")
    if high is not None and value > high:
        raise ConfigError(f"{dotted} must be <= {high}, got {value!r}")


def _numbers(cfg: DictConfig, dotted: str, *, optional=False, scalar_ok=False, **limits):
    """A list of numbers (or, with ``scalar_ok``, one number), each checked like ``_number``."""
    value = OmegaConf.select(cfg, dotted)
    if optional and value is None:
        return
    if scalar_ok and not OmegaConf.is_list(value):
        return _check_number(value, dotted, **limits)
    if not OmegaConf.is_list(value) or len(value) == 0:
        raise ConfigError(f"{dotted} must be a non-empty list of numbers, got {_plain(value)!r}")
    for i, item in enumerate(value):
        _check_number(item, f"{dotted}[{i}]", **limits)


def _plain(value):
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def _one_of(cfg: DictConfig, dotted: str, choices) -> None:
    value = OmegaConf.select(cfg, dotted)
    if value not in choices:
        raise ConfigError(f"{dotted} must be one of {', '.join(map(str, choices))}, got {value!r}")


def optim_lr_decay(cfg: DictConfig) -> tuple:
    """(``optim.lr_decay``, ``optim.lr_decay_updates``); a constant rate for the saved config of a
    run from before the keys existed."""
    return cfg.optim.get("lr_decay", 1.0), cfg.optim.get("lr_decay_updates", 6000)


def agent_n_steps(cfg: DictConfig):
    """``agent.n_steps``; 1 (one-step TD) for the saved config of a run from before the key existed."""
    return cfg.agent.get("n_steps", 1)


def check_train_config(cfg: DictConfig) -> None:
    """Range and type checks with messages that name the key, before anything is built or written."""
    _number(cfg, "seed", low=0, high=2**32 - 1, integer=True)  # numpy's seed range
    _number(cfg, "threads", low=1, integer=True, optional=True)
    _number(cfg, "env.num_envs", low=1, integer=True)
    _number(cfg, "env.max_round_trips", low=1, integer=True)
    _number(cfg, "env.min_round_trips", low=1, integer=True, optional=True)
    _number(cfg, "env.reward_center")
    _number(cfg, "env.reward_scale", low=0, low_open=True)
    _number(cfg, "train.total_frames", low=1, integer=True)
    _number(cfg, "train.max_minutes", low=0, low_open=True, optional=True)
    _number(cfg, "train.eval_every_frames", low=1, integer=True, optional=True)
    _number(cfg, "train.stop_at_success", low=0, high=1, optional=True)
    _number(cfg, "train.checkpoint_every_frames", low=1, integer=True, optional=True)
    _number(cfg, "collector.frames_per_batch", low=1, integer=True)
    _number(cfg, "collector.num_workers", low=1, integer=True)
    _number(cfg, "collector.worker_threads", low=1, integer=True, optional=True)
    _number(cfg, "optim.lr", low=0, low_open=True)
    decay, decay_updates = optim_lr_decay(cfg)
    _check_number(decay, "optim.lr_decay", low=0, high=1, low_open=True)
    _check_number(decay_updates, "optim.lr_decay_updates", low=1, integer=True)
    _number(cfg, "optim.batch_size", low=1, integer=True)
    _number(cfg, "optim.updates_per_frame", low=0, low_open=True)
    _number(cfg, "optim.max_grad_norm", low=0, low_open=True)
    _number(cfg, "optim.weight_decay", low=0)
    _number(cfg, "agent.gamma", low=0, high=1)
    _check_number(agent_n_steps(cfg), "agent.n_steps", low=1, integer=True)
    _one_of(cfg, "agent.loss_function", ("l1", "l2", "smooth_l1"))
    _one_of(cfg, "agent.target.kind", ("soft", "hard"))
    _number(cfg, "agent.target.tau", low=0, high=1, low_open=True)
    _number(cfg, "agent.target.interval", low=1, integer=True)
    _one_of(cfg, "agent.exploration.kind", ("exponential", "linear"))
    _number(cfg, "agent.exploration.start", low=0, high=1)
    _number(cfg, "agent.exploration.end", low=0, high=cfg.agent.exploration.start)
    _number(cfg, "agent.exploration.decay_frames", low=0, low_open=True)
    _numbers(cfg, "agent.network.channels", low=1, integer=True)
    _numbers(cfg, "agent.network.hidden", low=1, integer=True)
    _number(cfg, "agent.network.kernel_size", low=1, integer=True)
    _number(cfg, "agent.network.pool", low=1, integer=True)
    _number(cfg, "agent.network.negative_slope", low=0)
    _one_of(cfg, "replay.kind", ("prioritized", "uniform"))
    _number(cfg, "replay.size", low=1, integer=True)
    _number(cfg, "replay.alpha", low=0)
    _number(cfg, "replay.beta", low=0)
    _number(cfg, "replay.init_random_frames", low=0, integer=True)
    _number(cfg, "eval.steps", low=1, integer=True, optional=True)
    _number(cfg, "eval.repeats", low=1, integer=True, optional=True)
    _number(cfg, "eval.max_round_trips", low=1, integer=True, optional=True)
    _number(cfg, "eval.min_round_trips", low=1, integer=True, optional=True)
    _number(cfg, "eval.success_r", optional=True)
    _number(cfg, "eval.hold_r", optional=True)
    _numbers(cfg, "eval.K", optional=True, scalar_ok=True)
    if OmegaConf.select(cfg, "eval.init_fields") is not None:
        _one_of(cfg, "eval.init_fields", ("sech", "noise"))
    _numbers(cfg, "eval.starts_deg", optional=True, scalar_ok=True)
    if cfg.collector.frames_per_batch % cfg.env.num_envs:
        raise ConfigError(f"collector.frames_per_batch ({cfg.collector.frames_per_batch}) must be a multiple of "
                          f"env.num_envs ({cfg.env.num_envs})")
    if cfg.collector.kind not in ("sync", "multi_sync", "multi_async", "ray"):
        raise ConfigError(f"collector.kind must be sync, multi_sync, multi_async or ray, got {cfg.collector.kind!r}")
    if cfg.collector.kind == "ray" and cfg.collector.sync:
        share, left = divmod(cfg.collector.frames_per_batch, int(cfg.collector.num_workers))
        if left or share % cfg.env.num_envs:
            raise ConfigError(f"collector.frames_per_batch ({cfg.collector.frames_per_batch}) must split over "
                              f"collector.num_workers ({cfg.collector.num_workers}) into multiples of env.num_envs "
                              f"({cfg.env.num_envs})")
    if agent_n_steps(cfg) > 1 and (cfg.collector.kind == "multi_async"
                                   or (cfg.collector.kind == "ray" and not cfg.collector.sync)):
        # n-step returns join each batch to the previous one, which needs the same envs in the same order
        raise ConfigError(f"agent.n_steps={cfg.agent.n_steps} needs batches from every env in turn: use "
                          f"collector=sync, multi_sync or ray with collector.sync=true, not {cfg.collector.kind}"
                          + (" with sync=false" if cfg.collector.kind == "ray" else ""))
    if cfg.logger.backend not in ("wandb", "csv", "tensorboard", "none"):
        raise ConfigError(f"logger.backend must be wandb, csv, tensorboard or none, got {cfg.logger.backend!r}")
    if cfg.logger.backend == "wandb" and cfg.logger.mode not in ("offline", "online", "disabled"):
        raise ConfigError(f"logger.mode must be offline, online or disabled, got {cfg.logger.mode!r}")
    _check_device(cfg.device)
    # the physics, the task and the Q-network check themselves; their errors name the config key
    from laserrl.agents.dqn import make_qnet
    from laserrl.envs.factory import make_params, make_task

    env_cfg, stage_cfg = OmegaConf.to_container(cfg.env, resolve=True), OmegaConf.to_container(cfg.stage, resolve=True)
    params = make_params(env_cfg)
    task = make_task(env_cfg, stage_cfg)
    net = cfg.agent.network
    try:
        make_qnet(task.num_actions, params.n, net.channels, net.kernel_size, net.pool, net.hidden, net.negative_slope)
    except ValueError as err:
        raise ConfigError(f"agent.network: {err}") from None


def _check_device(device) -> None:
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ConfigError(f"device: {err}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device={device!r} but CUDA is not available here; use device=cpu")


def flat_config(cfg: DictConfig) -> dict:
    """Resolved config as {"optim.lr": 0.001, ...} with scalar values (TensorBoard's hparams need them)."""
    out: dict = {}

    def walk(node, prefix):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}{k}.")
        else:
            key = prefix[:-1]
            out[key] = node if isinstance(node, (int, float, str, bool)) and node is not None else str(node)

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return out


def log_config(logger, cfg: DictConfig) -> None:
    """Log the resolved config: nested for W&B, flattened for the other backends."""
    if cfg.logger.backend == "wandb":
        logger.log_hparams(OmegaConf.to_container(cfg, resolve=True))
    else:
        logger.log_hparams(flat_config(cfg))


def make_logger(cfg: DictConfig, run_dir: Path, state: dict | None = None, frames: int = 0):
    """TorchRL logger writing into the run directory (wandb offline needs no account or network).

    ``state`` (the ``Logger.state_dict()`` of a checkpoint at ``frames``) continues a run's logs:
    the CSV files are rewritten to exactly the records of the checkpoint (later ones, logged
    before a kill, are dropped), TensorBoard is told to discard events after ``frames``
    (its purge-step mechanism), and W&B resumes the same run id.
    """
    from torchrl.record.loggers import CSVLogger, TensorboardLogger, WandbLogger

    backend = cfg.logger.backend
    name = cfg.logger.name or f"{cfg.stage.name}-seed{cfg.seed}"
    if backend == "none":
        return None
    if backend == "csv":
        if state is not None:
            shutil.rmtree(run_dir / "logs" / name / "scalars", ignore_errors=True)
        logger = CSVLogger(exp_name=name, log_dir=str(run_dir / "logs"))
        for key, records in (state or {}).get("local", {}).get("scalars", {}).items():
            for step, value in records:
                logger.log_scalar(key, value, step=step)
        return logger
    if backend == "tensorboard":
        logger = TensorboardLogger(exp_name=name, log_dir=str(run_dir / "logs"))
        if state is not None:  # what SummaryWriter(purge_step=frames + 1) writes
            from tensorboard.compat.proto.event_pb2 import Event, SessionLog

            logger.experiment._get_file_writer().add_event(
                Event(step=frames + 1, session_log=SessionLog(status=SessionLog.START)))
        return logger
    run_id = (state or {}).get("local", {}).get("id")
    logger = WandbLogger(exp_name=name, offline=cfg.logger.mode == "offline", save_dir=str(run_dir),
                         project=cfg.logger.project, mode=cfg.logger.mode, log_env_packages=False, id=run_id)
    if state is not None:
        logger.load_state_dict(state)
    return logger
