"""Experiments made of several training runs: the curriculum and transfer across K.

Both run the ordinary ``train`` once per sub-run, in sub-directories of the run
directory, with the sub-run's config written out in full by ``train``'s checkpoint.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from laserrl.checkpoint import CheckpointError
from laserrl.config import ConfigError
from laserrl.paths import CONF_DIR
from laserrl.train import check_train_config, train


def run_curriculum(cfg: DictConfig) -> dict:
    """Train ``curriculum.stages`` in order, each warm-started from the previous stage's
    checkpoint (the Q-head grows by ``laserrl.warmstart.head_mapping``); every stage runs
    in its own sub-directory ``NN-stage`` of the run directory. Every stage's config is
    checked before the first stage trains, so that a wrong value in a later stage does not
    cost the earlier stages' training."""
    stage_cfgs = curriculum_stage_configs(cfg)
    for name, sub in stage_cfgs:
        try:
            check_train_config(sub)
        except ValueError as err:  # ConfigError is one; the stage's name says which block to fix
            kind = ConfigError if isinstance(err, ConfigError) else ValueError
            raise kind(f"curriculum stage {name!r}: {err}") from err
    previous = cfg.init_from
    summary: dict = {}
    for i, (name, sub) in enumerate(stage_cfgs):
        print(f"curriculum stage {i + 1}/{len(stage_cfgs)}: {name} (warm start: {previous or 'none'})")
        summary = train(OmegaConf.merge(sub, {"init_from": previous}))
        previous = summary["model"]
    return summary


def curriculum_stage_configs(cfg: DictConfig) -> list[tuple[str, DictConfig]]:
    """(stage name, the config its run trains with) for each of ``curriculum.stages``, without
    the warm start (``init_from`` is the previous stage's model, known once it has trained)."""
    stages = list(cfg.curriculum.stages)
    per_stage = {key: list(cfg.curriculum[key]) for key in ("total_frames", "max_minutes")
                 if cfg.curriculum.get(key) is not None}
    for key, values in per_stage.items():
        if len(values) != len(stages):
            raise ConfigError(f"curriculum.{key} needs one entry per stage ({len(stages)}), got {len(values)}")
    known = sorted(p.stem for p in (Path(CONF_DIR) / "stage").glob("*.yaml"))
    for name in stages:
        if name not in known:
            raise ConfigError(f"curriculum.stages: unknown stage {name!r}; stages: {known}")
    out = []
    for i, name in enumerate(stages):
        path = Path(CONF_DIR) / "stage" / f"{name}.yaml"
        sub = _sub_config(cfg, "curriculum", Path(cfg.run_dir) / f"{i + 1:02d}-{name}", init_from=None)
        # the stage file replaces the stage (no keys of the previous stage may linger)
        sub.stage = OmegaConf.merge(OmegaConf.load(path), cfg.curriculum.get("stage_overrides", {}).get(name, {}))
        extra = cfg.curriculum.get("config_overrides", {}).get(name)
        if extra:  # e.g. a lower starting exploration rate for warm-started stages
            sub = OmegaConf.merge(sub, extra)
        # per-stage budgets last; each stage evaluates with its own protocol
        sub = OmegaConf.merge(sub, {"train": {key: values[i] for key, values in per_stage.items()}})
        out.append((name, sub))
    return out


def _sub_config(cfg: DictConfig, drop: str, run_dir: Path, **changes) -> DictConfig:
    """The run config without the experiment block ``drop``, in ``run_dir``, with ``changes`` merged in."""
    sub = OmegaConf.to_container(cfg, resolve=True)
    sub.pop(drop)
    sub["run_dir"] = str(run_dir)
    return OmegaConf.merge(OmegaConf.create(sub), OmegaConf.create(changes))


def run_transfer(cfg: DictConfig) -> dict:
    """Fine-tune ``transfer.base`` to every K in ``transfer.Ks`` and train from scratch at
    the same K, both stopping once the greedy success rate reaches
    ``train.stop_at_success``; writes ``transfer.json`` and ``transfer.md`` (frames to
    success of each, and their ratio). Returns the mean fine-tune / scratch frame ratio.

    ``transfer.scratch_from``: the scratch run goes through a curriculum whose earlier stages
    do not depend on K (e.g. the two-controller stage at K = 0.1 before the four-controller
    one): it starts from that stage's model, and the frames of that model and of those it was
    warm-started from (``laserrl.model.frames_since_scratch``) count towards its frames."""
    t = cfg.transfer
    if not t.base:
        raise ConfigError("transfer.base: give the model to fine-tune, e.g. transfer.base=zoo:siso or a run directory")
    from laserrl.model import frames_since_scratch, load_model

    try:
        load_model(t.base)
    except CheckpointError as err:
        raise ConfigError(f"transfer.base: {err}") from None
    scratch_from, prior_frames = t.get("scratch_from"), 0
    if scratch_from:
        try:
            prior_frames = frames_since_scratch(load_model(scratch_from))
        except CheckpointError as err:
            raise ConfigError(f"transfer.scratch_from: {err}") from None
        if prior_frames is None:
            raise ConfigError(f"transfer.scratch_from: {scratch_from} does not record the frames of the models it was "
                              "warm-started from (its card's frames_since_scratch)")
    if cfg.train.get("stop_at_success") is None or not cfg.train.get("eval_every_frames"):
        raise ConfigError("transfer needs train.eval_every_frames and train.stop_at_success to count frames to success")
    by_K = _settings_by_K(t.get("by_K"))
    rows = []
    for K in [float(k) for k in t.Ks]:
        row = {"K": K}
        # per-K settings (e.g. longer episodes where the locks lie far from the starts) apply to both runs
        at_K = next((s for k, s in by_K.items() if math.isclose(k, K, abs_tol=1e-9)), None)
        runs = [("finetune", t.base, t.finetune, 0)]
        if t.scratch is not None:
            runs.append(("scratch", scratch_from or None, t.scratch, prior_frames))
        for label, init, overrides, before in runs:
            run_dir = Path(cfg.run_dir) / f"K{K:+.2f}-{label}"
            done = run_dir / "summary.json"
            if done.exists():  # finished earlier (an interrupted or parallel transfer run): reuse it
                print(f"transfer: K = {K:g}, {label}: reusing {done}")
                summary = json.loads(done.read_text())
            else:
                sub = _sub_config(cfg, "transfer", run_dir, init_from=init, stage={"K": K}, eval={"K": K})
                for extra in (overrides, at_K):  # per-K settings win
                    if extra:
                        sub = OmegaConf.merge(sub, extra)
                print(f"transfer: K = {K:g}, {label}")
                summary = train(sub)
            reached = summary["frames_to_success"]
            row[label] = {"frames_to_success": None if reached is None else before + reached,
                          "frames": before + summary["frames"], "frames_before": before,
                          "train_seconds": summary["train_seconds"],
                          "success_rate": summary.get("eval/success_rate")}
        if t.scratch is not None:
            f, s = row["finetune"]["frames_to_success"], row["scratch"]["frames_to_success"]
            # a run that never succeeded counts with all its frames (a lower bound on its need)
            f_eff = f if f is not None else row["finetune"]["frames"]
            s_eff = s if s is not None else row["scratch"]["frames"]
            row["ratio"] = f_eff / s_eff if s_eff else math.nan
            row["ratio_is_bound"] = f is None or s is None
        rows.append(row)
    out = {"base": str(t.base), "scratch_from": scratch_from or None, "scratch_frames_before": prior_frames,
           "stop_at_success": cfg.train.stop_at_success, "rows": rows}
    Path(cfg.run_dir).mkdir(parents=True, exist_ok=True)
    (Path(cfg.run_dir) / "transfer.json").write_text(json.dumps(out, indent=1))
    (Path(cfg.run_dir) / "transfer.md").write_text(transfer_table(out))
    print(transfer_table(out))
    ratios = [r["ratio"] for r in rows if "ratio" in r]
    return {"transfer/mean_ratio": sum(ratios) / len(ratios) if ratios else math.nan, "rows": rows}


def _settings_by_K(by_K) -> dict[float, dict]:
    """``transfer.by_K``: {K: config overrides}; keys are numbers or numeric strings."""
    out = {}
    for key, settings in (by_K or {}).items():
        try:
            K = float(key)
        except (TypeError, ValueError):
            raise ConfigError(f"transfer.by_K: key {key!r} is not a birefringence value K") from None
        if not math.isfinite(K):
            raise ConfigError(f"transfer.by_K: key {key!r} is not a finite K")
        out[K] = settings
    return out


def transfer_table(out: dict) -> str:
    """Markdown table of a transfer.json."""
    def fmt(run):
        if run is None:
            return "-"
        f = run["frames_to_success"]
        return f"{f:,}" if f is not None else f"not within {run['frames']:,}"
    lines = ["| K | fine-tune: frames to success | scratch: frames to success | fine-tune / scratch |",
             "|---:|---:|---:|---:|"]
    for r in out["rows"]:
        ratio = r.get("ratio")
        ratio_s = "-" if ratio is None else (f"{ratio:.2f}" + (" (bound)" if r.get("ratio_is_bound") else ""))
        lines.append(f"| {r['K']:g} | {fmt(r.get('finetune'))} | {fmt(r.get('scratch'))} | {ratio_s} |")
    if out.get("scratch_from"):
        lines.append(f"\nScratch frames include the {out['scratch_frames_before']:,} frames of the curriculum's "
                     f"earlier stages ({out['scratch_from']} and the models it was warm-started from).")
    return "\n".join(lines) + "\n"
