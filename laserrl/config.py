"""Config checks, loggers, and turning user errors into one clear line."""
from __future__ import annotations

import contextlib
import shutil
import sys
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from laserrl.checkpoint import CheckpointError
from laserrl.validate import ConfigError, check_number


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


def _number(cfg: DictConfig, dotted: str, **limits):
    """``laserrl.validate.check_number`` of the value at ``dotted`` in ``cfg``."""
    return check_number(OmegaConf.select(cfg, dotted), dotted, **limits)


def optim_lr_decay(cfg: DictConfig) -> tuple:
    """(``optim.lr_decay``, ``optim.lr_decay_updates``); a constant rate for the saved config of a
    run from before the keys existed."""
    return cfg.optim.get("lr_decay", 1.0), cfg.optim.get("lr_decay_updates", 6000)


def agent_n_steps(cfg: DictConfig):
    """``agent.n_steps``; 1 (one-step TD) for the saved config of a run from before the key existed."""
    return cfg.agent.get("n_steps", 1)


def check_logger_config(cfg: DictConfig) -> None:
    if cfg.logger.backend not in ("wandb", "csv", "tensorboard", "none"):
        raise ConfigError(f"logger.backend must be wandb, csv, tensorboard or none, got {cfg.logger.backend!r}")
    if cfg.logger.backend == "wandb" and cfg.logger.mode not in ("offline", "online", "disabled"):
        raise ConfigError(f"logger.mode must be offline, online or disabled, got {cfg.logger.mode!r}")


def check_device(device) -> None:
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

    check_logger_config(cfg)
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
