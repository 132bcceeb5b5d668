"""The console scripts: one Hydra app per command, all configured from ``laserrl/conf``.

    laserrl-train     ``laserrl.train`` (with ``experiment=curriculum`` / ``transfer_k``: ``laserrl.experiments``)
    laserrl-eval      ``laserrl.evaluate``
    laserrl-control   ``laserrl.control.app``
    laserrl-report    ``laserrl.report.app``

Each app returns the metric a sweeper optimises (``metric=...``); user errors end the
command with one line on stderr (``laserrl.config.user_errors``).
"""
from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from laserrl.config import ConfigError, user_errors
from laserrl.paths import CONF_DIR


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="config")
def _train_app(cfg: DictConfig) -> float:
    from laserrl.experiments import run_curriculum, run_transfer
    from laserrl.resume import RunInterrupted
    from laserrl.train import resume_run, train

    try:
        with user_errors("laserrl-train"):
            if cfg.get("resume"):
                summary = resume_run(cfg)
            elif cfg.get("curriculum"):
                summary = run_curriculum(cfg)
            elif cfg.get("transfer"):
                summary = run_transfer(cfg)
            else:
                summary = train(cfg)
    except RunInterrupted as stop:
        print(f"laserrl-train: {stop}", file=sys.stderr)
        sys.exit(128 + stop.signum)
    metric = summary.get(cfg.metric)
    return float(metric) if metric is not None else float("nan")


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="eval")
def _eval_app(cfg: DictConfig) -> float:
    from laserrl.evaluate import evaluate_bank, evaluate_checkpoint

    with user_errors("laserrl-eval"):
        stage = OmegaConf.to_container(cfg.stage, resolve=True) if cfg.get("stage") else None
        eval_cfg = OmegaConf.to_container(cfg.eval, resolve=True)
        eval_cfg["physics"] = OmegaConf.to_container(cfg.env.physics, resolve=True) if cfg.get("env") else {}
        if cfg.get("bank"):
            bank = OmegaConf.to_container(cfg.bank, resolve=True) if OmegaConf.is_list(cfg.bank) else cfg.bank
            if not isinstance(bank, list):
                raise ConfigError(f"bank: give a list of checkpoints, e.g. bank=[K0.pt,[K0.2_seed0.pt,K0.2_seed1.pt]], got {bank!r}")
            trial = OmegaConf.to_container(cfg.bank_trial, resolve=True) if cfg.get("bank_trial") else None
            result = evaluate_bank(bank, eval_cfg, cfg.run_dir, stage, single=cfg.checkpoint or None, trial=trial)
            return float(max(result["grid_success"][rule] for rule in ("max_q", "trial")))  # the best K-blind rule
        if cfg.checkpoint is None or cfg.checkpoint == "":
            raise ConfigError("give the checkpoint to evaluate: laserrl-eval checkpoint=PATH (or bank=[PATH,...])")
        result = evaluate_checkpoint(cfg.checkpoint, eval_cfg, cfg.run_dir, stage)
    return float(result["success_rate"])


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="control")
def _control_app(cfg: DictConfig) -> float:
    from laserrl.control.app import run_control, sweep_metric

    with user_errors("laserrl-control"):
        return sweep_metric(run_control(cfg), cfg)


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="report")
def _report_app(cfg: DictConfig) -> None:
    from laserrl.report.app import run_report

    with user_errors("laserrl-report"):
        run_report(cfg)


def train_main() -> None:
    _train_app()


def eval_main() -> None:
    _eval_app()


def control_main() -> None:
    _control_app()


def report_main() -> None:
    _report_app()
