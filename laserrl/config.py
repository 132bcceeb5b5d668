"""Config checks, loggers, and turning user errors into one clear line."""
from __future__ import annotations

import contextlib
import math
import sys
from pathlib import Path

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


def _number(cfg: DictConfig, dotted: str, *, low=None, high=None, integer=False, low_open=False):
    value = OmegaConf.select(cfg, dotted)
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and int(value) != value):
        raise ConfigError(f"{dotted} must be {kind}, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{dotted} must be finite, got {value!r}")
    if low is not None and (value <= low if low_open else value < low):
        raise ConfigError(f"{dotted} must be {'>' if low_open else '>='} {low}, got {value!r}")
    if high is not None and value > high:
        raise ConfigError(f"{dotted} must be <= {high}, got {value!r}")


def check_train_config(cfg: DictConfig) -> None:
    """Range and type checks with messages that name the key."""
    _number(cfg, "seed", integer=True)
    _number(cfg, "env.num_envs", low=1, integer=True)
    _number(cfg, "env.max_round_trips", low=1, integer=True)
    _number(cfg, "train.total_frames", low=1, integer=True)
    _number(cfg, "collector.frames_per_batch", low=1, integer=True)
    _number(cfg, "optim.lr", low=0, low_open=True)
    _number(cfg, "optim.batch_size", low=1, integer=True)
    _number(cfg, "optim.updates_per_frame", low=0, low_open=True)
    _number(cfg, "optim.max_grad_norm", low=0, low_open=True)
    _number(cfg, "optim.weight_decay", low=0)
    _number(cfg, "agent.gamma", low=0, high=1)
    _number(cfg, "replay.size", low=1, integer=True)
    _number(cfg, "replay.alpha", low=0)
    _number(cfg, "replay.beta", low=0)
    _number(cfg, "replay.init_random_frames", low=0, integer=True)
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
    if cfg.logger.backend not in ("wandb", "csv", "tensorboard", "none"):
        raise ConfigError(f"logger.backend must be wandb, csv, tensorboard or none, got {cfg.logger.backend!r}")
    if cfg.logger.backend == "wandb" and cfg.logger.mode not in ("offline", "online", "disabled"):
        raise ConfigError(f"logger.mode must be offline, online or disabled, got {cfg.logger.mode!r}")


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


def make_logger(cfg: DictConfig, run_dir: Path):
    """TorchRL logger writing into the run directory (wandb offline needs no account or network)."""
    from torchrl.record.loggers import CSVLogger, TensorboardLogger, WandbLogger

    backend = cfg.logger.backend
    name = cfg.logger.name or f"{cfg.stage.name}-seed{cfg.seed}"
    if backend == "none":
        return None
    if backend == "csv":
        return CSVLogger(exp_name=name, log_dir=str(run_dir / "logs"))
    if backend == "tensorboard":
        return TensorboardLogger(exp_name=name, log_dir=str(run_dir / "logs"))
    return WandbLogger(exp_name=name, offline=cfg.logger.mode == "offline", save_dir=str(run_dir),
                       project=cfg.logger.project, mode=cfg.logger.mode, log_env_packages=False)
