"""``laserrl-report``: regenerate the paper's figures and docs/reproduction.md (laserrl/conf/report.yaml).

    laserrl-report      # the zoo's models (laserrl/conf/report.yaml)
    laserrl-report report.checkpoints.siso=RUN report.checkpoints.duo=CURR/02-duo \
        report.checkpoints.miso=CURR/03-miso report.checkpoints.k_base=BASE/03-miso \
        'report.checkpoints.bank=[K0,K0.2,K0.4]' \
        'report.results.transfer=[T/transfer.json]' report.results.generalisation=G/eval.json
    laserrl-report report.checkpoints.siso=null ...   # null: train small models on the spot first
"""
from __future__ import annotations

import json
import os
import shlex
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from laserrl.model import load_model as read_model, machine_line
from laserrl.config import ConfigError
from laserrl.report.claims import build_claims, markdown, to_json
from laserrl.report.context import ReportContext, bank_entries, bank_paths, grid, load_model, producing_command
from laserrl.results import read_json
from laserrl.report.figures import FIGURES, draw_figures
from laserrl.report.spot import train_missing


def report_command() -> str:
    """This run's command line, from Hydra's record of the task overrides."""
    from hydra.core.hydra_config import HydraConfig

    try:
        overrides = list(HydraConfig.get().overrides.task)
    except ValueError:  # called outside a Hydra app
        overrides = []
    return " ".join(["laserrl-report", *(shlex.quote(o) for o in overrides)])


def _check_inputs(rcfg: dict) -> None:
    """Fail fast, before any training or simulation, on result files that are not there."""
    results = rcfg["results"]
    if results.get("generalisation"):
        read_json(results["generalisation"], "report.results.generalisation")
    for path in results.get("transfer") or []:
        read_json(path, "report.results.transfer")
    for d in results.get("train_to_success") or []:
        if not Path(d).is_dir():
            raise ConfigError(f"report.results.train_to_success: no such run directory {d}")
    if not rcfg["fig3_starts"]:
        raise ConfigError("report.fig3_starts: give at least one start alpha1 to show in detail, e.g. [-36,-28,-12]")
    for key in ("alpha1_deg", "map_alpha1_deg", "map_alpha2_deg"):
        grid(rcfg["landscape"][key], f"report.landscape.{key}")
    if rcfg["figures"] is not None:
        unknown = sorted(set(rcfg["figures"]) - set(FIGURES))
        if unknown:
            raise ConfigError(f"report.figures: unknown figure(s) {unknown}; figures: {list(FIGURES)}")


def _write(path: Path, text: str) -> None:
    """Write atomically: a crash leaves the previous file intact."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def run_report(cfg: DictConfig) -> dict:
    """Everything ``laserrl-report`` does; returns the content of report.json."""
    started = time.perf_counter()
    load_start = os.getloadavg()[0]
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    rcfg = OmegaConf.to_container(cfg.report, resolve=True)
    run_dir = Path(cfg.run_dir)
    out_dir = Path(rcfg["out_dir"]).resolve()
    _check_inputs(rcfg)
    commands = {"report": report_command()}
    checkpoints = {role: rcfg["checkpoints"].get(role) for role in ("siso", "duo", "miso", "k_base")}
    bank = bank_entries(rcfg["checkpoints"].get("bank"))
    models = {role: load_model(path, role) for role, path in checkpoints.items() if path}  # fail fast
    if rcfg["checkpoints"].get("any_k"):  # beyond the paper: not trained on the spot
        models["any_k"] = load_model(rcfg["checkpoints"]["any_k"], "any_k")
    for path in bank_paths(bank):
        read_model(path)
    trained = train_missing(rcfg["train"], run_dir, checkpoints, bank, rcfg["results"], bool(rcfg.get("train_bank")))
    for role in ("siso", "duo", "miso", "k_base"):
        if role in trained:
            models[role] = load_model(checkpoints[role], role, trained[role]["command"])
        commands[role] = models[role].command or f"(not recorded: {models[role].path})"
    if bank:
        commands["bank"] = (trained["bank"]["command"] if "bank" in trained else
                            "; ".join(dict.fromkeys(producing_command(p) or p for p in bank_paths(bank))))
    ctx = ReportContext(rcfg, run_dir, models, bank, commands, int(cfg.seed))
    ctx.run_commands.update({Path(r["run_dir"]).resolve(): r["command"] for r in trained.values()})
    figures = draw_figures(ctx, out_dir / "figures", rcfg["figures"])
    rows = build_claims(ctx)
    minutes = (time.perf_counter() - started) / 60
    meta = {"machine": f"{machine_line()}, torch threads {torch.get_num_threads()}",
            "date": time.strftime("%Y-%m-%d"),
            "load": f"{load_start:.1f} at the start, {os.getloadavg()[0]:.1f} at the end",
            "minutes": minutes, "training_minutes": sum(r["minutes"] for r in trained.values()),
            "trained_on_the_spot": trained}
    out_dir.mkdir(parents=True, exist_ok=True)
    doc = out_dir / "reproduction.md"
    _write(doc, markdown(ctx, rows, figures, out_dir, meta))
    report = {"claims": to_json(rows), "figures": figures, "commands": commands, "meta": meta, "numbers": ctx.numbers,
              "checkpoints": {**{r: m.path for r, m in models.items()}, "bank": bank}}
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "report.json").write_text(json.dumps(report, indent=1, default=str))
    print(f"report: {doc} ({minutes:.1f} min)")
    return report
