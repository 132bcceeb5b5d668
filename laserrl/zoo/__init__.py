"""The model zoo: trained agents shipped with laserrl, named ``zoo:NAME`` wherever a model is accepted.

    laserrl-zoo list                 # the models, their task and recorded success
    laserrl-zoo describe siso        # the model card: command, commit, machine, frames, time, evaluation
    laserrl-eval checkpoint=zoo:siso # re-evaluate it on its protocol

Each model is a directory ``laserrl/zoo/NAME`` in the model format of ``laserrl.model``
(model.safetensors + model.json, whose ``card`` is the model card), with the run's
``history.json`` (the training curve) and ``eval.json`` (the evaluation on the task's protocol).
``laserrl-zoo add RUN NAME`` copies a trained run's model in (for maintainers).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from laserrl import model as _model
from laserrl.agents.qnet import saved_head
from laserrl.checkpoint import one_line_errors
from laserrl.model import META, WEIGHTS, ModelError, read_meta, zoo_path

MAX_BYTES = 2_000_000  # a zoo model with its files: weights (~0.6 MB) and JSON
names = _model.zoo_names


def card(name: str) -> dict:
    meta = read_meta(zoo_path(name))
    return {"name": name, "stage": meta.get("stage"), "K": meta.get("K"), "actions": meta.get("actions"),
            "observation": meta.get("observation", "fields"), "memory": meta.get("memory", {"history": 1}),
            "card": meta.get("card", {}), "eval": meta.get("eval", {}),
            "heldout": meta.get("heldout"),
            "head": saved_head(meta.get("config"))}


def _eval_line(ev: dict) -> str:
    if not ev:
        return "not evaluated"
    rule = (f"final r >= {ev.get('success_r')}" if ev.get("hold_r") is None
            else f"reach r >= {ev.get('success_r')}, hold r >= {ev.get('hold_r')}"
            + (f", locked for at least the last {ev['held_steps']} steps" if ev.get("held_steps") else ""))
    runs = len(ev.get("per_start", [])) or None
    return (f"success {ev.get('success_rate'):.2f}, mean final r {ev.get('mean_final_reward'):.4f} "
            f"({ev.get('steps')} steps, {rule}, K {ev.get('K')}, repeats {ev.get('repeats')}, seed {ev.get('seed')}"
            + (f", {runs} rollouts" if runs else "") + ")")


def describe(name: str) -> str:
    c = card(name)
    k = c["card"]
    lines = [f"zoo:{name}: stage {c['stage']} (turns {', '.join(c['actions']['controlled'])} by "
             f"{c['actions']['steps_deg']} deg), K = {c['K']}, observation {c['observation']}"
             + (f" (the last {c['memory']['history']} stacked)" if c["memory"].get("history", 1) > 1 else "")
             + (f", remembered by a GRU of {c['memory']['gru_size']} units" if c["memory"].get("gru_size") else "")
             + (f", {c['head']} Q-head" if c["head"] != "joint" else ""),
             f"  trained by:  {k.get('command') or 'not recorded'}",
             f"  commit:      {k.get('commit') or 'not recorded'} (laserrl {k.get('laserrl_version')})",
             f"  machine:     {k.get('machine') or 'not recorded'}, {k.get('date') or ''}",
             f"  training:    {k.get('frames')} frames ({k.get('episodes')} episodes), "
             f"{(k.get('train_seconds') or 0) / 60:.1f} min"
             + (f"; {k['frames_since_scratch']} frames since scratch (with the models it was warm-started from)"
                if k.get("frames_since_scratch") not in (None, k.get("frames")) else ""),
             f"  evaluation:  {_eval_line(c['eval'])}"]
    if c.get("heldout"):
        lines.append(f"  held out:    {_eval_line(c['heldout'])}")
    if k.get("notes"):
        lines.append(f"  notes:       {k['notes']}")
    return "\n".join(lines)


def max_bytes(name: str) -> int:
    """The most a zoo model may take: ``MAX_BYTES`` per member of an ensemble."""
    return MAX_BYTES * int(json.loads((zoo_path(name) / "model.json").read_text()).get("ensemble", 1))


def size(name: str) -> int:
    return sum(p.stat().st_size for p in zoo_path(name).rglob("*") if p.is_file())


def eval_summary(result: dict) -> dict:
    """An eval.json without its per-rollout rows (what model.json keeps)."""
    return {k: v for k, v in result.items() if k != "per_start"}


def relative_paths(value, base: Path):
    """``value`` (JSON data) with every absolute path under ``base`` written relative to it."""
    if isinstance(value, dict):
        return {k: relative_paths(v, base) for k, v in value.items()}
    if isinstance(value, list):
        return [relative_paths(v, base) for v in value]
    if isinstance(value, str) and Path(value).is_absolute() and Path(value).is_relative_to(base):
        return Path(value).relative_to(base).as_posix()
    return value


def add(run: str | Path, name: str, heldout: str | Path | None = None, **card_changes) -> Path:
    """Copy the model of the run ``run`` (or a model directory) into the zoo as ``name``, with
    its history.json and eval.json (the evaluation on the task's protocol); ``heldout``: the
    eval.json of an evaluation on starts or noise draws never used in training or to choose
    the weights; ``card_changes`` update the model card. Refuses an existing name.

    The paths the run recorded (its directory, the model it was warm-started from, the
    checkpoint evaluated) are kept relative to the folder that holds the run, or the curriculum
    or transfer experiment that made it (``runs/NAME/03-miso`` is kept as ``NAME/03-miso``):
    provenance, without the maintainer's machine."""
    from laserrl.model import model_dir, update_model_meta

    if not _model._ZOO_NAME.match(name):
        raise ModelError(f"zoo name {name!r}: use lower-case letters, digits, '.', '+' and '-'")
    target = _model.ZOO_DIR / name
    if target.exists():
        raise ModelError(f"zoo:{name} exists already; remove {target} first to replace it")
    source = model_dir(run)
    meta = read_meta(source)
    run_dir = _model.record_dir(source)
    base = run_dir.resolve().parent.parent
    target.mkdir()
    try:
        for f in (WEIGHTS, META):
            shutil.copy2(source / f, target / f)
        if (run_dir / "history.json").is_file():
            shutil.copy2(run_dir / "history.json", target / "history.json")
        changes = {"config": meta.get("config", {}), "card": {**meta.get("card", {}), **card_changes}}
        if (run_dir / "eval.json").is_file():
            evaluation = relative_paths(json.loads((run_dir / "eval.json").read_text()), base)
            (target / "eval.json").write_text(json.dumps(evaluation, indent=1))
            changes["eval"] = eval_summary(evaluation)
        if heldout is not None:
            changes["heldout"] = eval_summary(json.loads(Path(heldout).read_text()))
        update_model_meta(target, **relative_paths(changes, base))
        if size(name) > max_bytes(name):
            raise ModelError(f"zoo:{name} would take {size(name)} bytes (> {max_bytes(name)})")
    except BaseException:
        shutil.rmtree(target, ignore_errors=True)
        raise
    return target


def main(argv: list[str] | None = None) -> int:
    """``laserrl-zoo list | describe NAME | path NAME | add RUN NAME [--heldout EVAL] [--card KEY=VALUE ...]``."""
    import argparse

    parser = argparse.ArgumentParser(prog="laserrl-zoo", description="the trained models shipped with laserrl")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="the models, their task and recorded success")
    for cmd, text in (("describe", "the model card of one model"), ("path", "the directory of one model")):
        sub.add_parser(cmd, help=text).add_argument("name")
    adding = sub.add_parser("add", help="copy a trained run's model into the zoo (maintainers)")
    adding.add_argument("run")
    adding.add_argument("name")
    adding.add_argument("--heldout", help="eval.json of an evaluation on starts or draws never used to choose the model")
    adding.add_argument("--card", action="append", default=[], metavar="KEY=VALUE",
                        help="set a model card field (JSON values are parsed: --card 'frames=32768')")
    args = parser.parse_args(argv)

    def run() -> None:
        if args.command == "list":
            for name in names():
                c = card(name)
                ev = c["eval"]
                success = f"success {ev['success_rate']:.2f}" if ev else "not evaluated"
                print(f"zoo:{name:12s} {c['stage']:5s} K={c['K']!s:6s} {c['observation']:8s} {success}  "
                      f"{size(name) / 1e6:.2f} MB")
        elif args.command == "describe":
            print(describe(args.name.removeprefix("zoo:")))
        elif args.command == "path":
            print(zoo_path(args.name.removeprefix("zoo:")))
        else:
            changes = {}
            for item in args.card:
                key, sep, value = item.partition("=")
                if not sep:
                    raise ModelError(f"--card {item!r}: give KEY=VALUE")
                try:
                    changes[key] = json.loads(value)
                except json.JSONDecodeError:
                    changes[key] = value
            print(f"added: {add(args.run, args.name, args.heldout, **changes)}")

    return one_line_errors("laserrl-zoo", run)


if __name__ == "__main__":
    raise SystemExit(main())
