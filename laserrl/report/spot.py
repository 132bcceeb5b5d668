"""Train the models a report was not given, with small budgets, by the ordinary training code.

Each model is ``laserrl.train.train`` (the bank: ``laserrl.experiments.run_transfer``) on a
training config composed from laserrl/conf exactly as ``laserrl-train OVERRIDES`` would compose it,
with ``report.train.common`` + ``report.train.<model>`` as the overrides. The siso model is
trained from scratch, duo from siso, miso and k_base (its four controllers at K = 0.1) from duo
(the curriculum), the bank by fine-tuning k_base at each K of ``transfer.Ks``.
"""
from __future__ import annotations

import re
import shlex
import time
from pathlib import Path
from typing import Any, Mapping

from omegaconf import DictConfig

from laserrl.paths import CONF_DIR


def compose_train_config(overrides: list[str], config_name: str = "config") -> DictConfig:
    """The config ``laserrl-train OVERRIDES`` runs with (``config_name="control"``: that of
    ``laserrl-control``), inside a Hydra app or not."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # inside laserrl-report: the same laserrl/conf directory
        return compose(config_name=config_name, overrides=overrides)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=config_name, overrides=overrides)


_PLAIN = re.compile(r"^[A-Za-z0-9_./:+-]+$")


def _value(value) -> str:
    """A value in Hydra's override grammar."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_value(v) for v in value) + "]"
    text = str(value)
    return text if _PLAIN.match(text) else "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def as_overrides(*layers: Mapping[str, Any]) -> list[str]:
    """Nested override dicts as Hydra overrides ``a.b=value``, later layers winning per key."""
    flat: dict[str, Any] = {}

    def walk(node, prefix):
        for key, value in node.items():
            if isinstance(value, Mapping):
                walk(value, f"{prefix}{key}.")
            else:
                flat[f"{prefix}{key}"] = value

    for layer in layers:
        walk(layer or {}, "")
    return [f"{key}={_value(value)}" for key, value in flat.items()]


def train_missing(train_cfg: dict, run_dir: Path, checkpoints: dict, bank: list[str], results: dict,
                  train_bank: bool = False) -> dict:
    """Train what ``checkpoints`` (role -> model or None) lack, and with ``train_bank`` an empty
    ``bank``, into ``run_dir/train``.

    Fills in ``checkpoints``, ``bank`` and (if empty) ``results["transfer"]`` in place;
    returns label -> {"command", "minutes", "run_dir"} of every run trained.
    """
    from laserrl.experiments import run_transfer
    from laserrl.train import train

    runs: dict[str, dict] = {}

    def run(label: str, extra: dict, runner):
        sub = run_dir / "train" / label
        overrides = as_overrides(train_cfg.get("common"), train_cfg.get(label), extra)
        cfg = compose_train_config([*overrides, f"run_dir={sub}"])
        command = " ".join(["laserrl-train", *(shlex.quote(o) for o in overrides), f"hydra.run.dir={sub}"])
        print(f"report: training {label} on the spot: {command}")
        started = time.perf_counter()
        runner(cfg)
        runs[label] = {"command": command, "minutes": (time.perf_counter() - started) / 60, "run_dir": str(sub)}
        return sub, cfg

    if not checkpoints.get("siso"):
        sub, _ = run("siso", {}, train)
        checkpoints["siso"] = str(sub / "model")
    if not checkpoints.get("duo"):
        sub, _ = run("duo", {"init_from": checkpoints["siso"]}, train)
        checkpoints["duo"] = str(sub / "model")
    if not checkpoints.get("miso"):
        sub, _ = run("miso", {"init_from": checkpoints["duo"]}, train)
        checkpoints["miso"] = str(sub / "model")
    if not checkpoints.get("k_base"):
        sub, _ = run("k_base", {"init_from": checkpoints["duo"]}, train)
        checkpoints["k_base"] = str(sub / "model")
    if not bank and train_bank:
        sub, cfg = run("bank", {"transfer": {"base": checkpoints["k_base"]}}, run_transfer)
        bank.extend(str(sub / f"K{float(K):+.2f}-finetune" / "model") for K in cfg.transfer.Ks)
        if not results.get("transfer"):
            results["transfer"] = [str(sub / "transfer.json")]
    return runs
