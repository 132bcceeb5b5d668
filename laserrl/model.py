"""Models people can share: the Q-network's weights as safetensors, everything else as JSON.

A model is a directory::

    model.safetensors   the Q-network's tensors (safetensors holds arrays only: nothing in it can run)
    model.json          format, laserrl version, the task (stage, controlled angles, action encoding, K),
                        the physics, the full training config, the evaluation on the task's protocol
                        and the model card (command, commit, machine, frames, training time)

Loading reads the JSON with ``json`` and the tensors with ``safetensors``; nothing is unpickled.
``laserrl-train`` writes ``RUN/model`` next to ``RUN/checkpoints``, whose training state
(optimizer, generators, replay buffer) serves ``resume=`` only (``laserrl.checkpoint``).

Wherever a model is accepted, ``zoo:NAME`` names one shipped with laserrl (``laserrl.zoo``),
and a run directory (``RUN`` or a curriculum stage ``RUN/03-miso``) names its ``model``.

An ensemble (``python -m laserrl.model ensemble OUT M1 M2 ...``) is a model of several
Q-networks trained for the same task (e.g. seeds of one recipe): model.json's ``ensemble``
gives their number, the tensors of member i are stored under ``members.i.``, and it acts on
the mean of their Q-values (``laserrl.agents.bank.MeanQ``).
"""
from __future__ import annotations

import json
import math
import functools
import os
import platform
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Mapping

import torch

from laserrl.checkpoint import FORMAT as CHECKPOINT_FORMAT
from laserrl.checkpoint import CheckpointError, load_checkpoint

FORMAT = "laserrl-model-1"
WEIGHTS, META = "model.safetensors", "model.json"
ZOO_PREFIX = "zoo:"
MAX_META_BYTES = 20_000_000  # a model.json is a few KB; refuse to parse anything absurd
#: how a joint action (an integer) maps to plate moves; laserrl.envs.laser_env.action_to_deltas
ACTION_ENCODING = ("base 3 over the controlled angles, first angle least significant; digit 0, 1, 2 turns that "
                   "angle by -step, 0, +step")


class ModelError(CheckpointError):
    """A model is missing, unreadable or not a laserrl model."""


#: the models shipped with laserrl (``laserrl.zoo``)
ZOO_DIR = Path(__file__).resolve().parent / "zoo"
_ZOO_NAME = re.compile(r"^[a-z0-9][a-z0-9.+-]*$")


def zoo_names() -> list[str]:
    return sorted(d.name for d in ZOO_DIR.iterdir() if (d / META).is_file()) if ZOO_DIR.is_dir() else []


def zoo_path(name: str) -> Path:
    """The directory of ``zoo:NAME``; a ModelError lists the zoo if there is no such model."""
    if not _ZOO_NAME.match(name) or not (ZOO_DIR / name / META).is_file():
        raise ModelError(f"zoo:{name}: no such model in the zoo; models: {', '.join(zoo_names()) or 'none'} "
                         "(laserrl-zoo list)")
    return ZOO_DIR / name


def package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("laserrl")
    except PackageNotFoundError:
        return "unknown"


def cpu_name() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return cpu


def machine_line() -> str:
    """CPU model, cores and Python, e.g. for a model card."""
    return f"{cpu_name()}, {os.cpu_count()} cores, torch {torch.__version__}, Python {platform.python_version()}"


@functools.lru_cache(maxsize=4)
def git_commit(where: str | os.PathLike | None = None) -> str | None:
    """The commit of the laserrl checkout that runs (None for an installed wheel); read once per
    process, so that a long run names the code it started with, not later commits to the checkout."""
    import subprocess

    where = Path(where or Path(__file__).parent)
    try:
        out = subprocess.run(["git", "-C", str(where), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "-C", str(where), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def model_metadata(config: Mapping[str, Any], num_actions: int, **extra) -> dict:
    """model.json for a network trained with ``config`` (a plain dict) and a ``num_actions`` head."""
    stage = dict(config["stage"])
    return {
        "format": FORMAT, "laserrl_version": package_version(), "stage": stage.get("name"),
        "num_actions": int(num_actions),
        "actions": {"controlled": list(stage["controlled"]), "steps_deg": list(stage["steps_deg"]),
                    "encoding": ACTION_ENCODING},
        "K": stage.get("K"), "physics": dict(config["env"].get("physics", {})),
        # what the network reads and remembers (the env config has the details: instruments, history, GRU)
        "observation": config["env"].get("observation", "fields"),
        "memory": {"history": int(config["env"].get("history", 1)),
                   **({"gru_size": int(config["env"]["gru_size"])} if config["env"].get("gru_size") is not None else {})},
        "config": dict(config), **extra,
    }


def _finite(obj):
    """JSON without NaN / inf (which the standard forbids): they become null."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def save_model(directory: str | os.PathLike, weights: Mapping[str, torch.Tensor], meta: Mapping[str, Any],
               replace: bool = False) -> Path:
    """Write a model directory (written beside it, then renamed into place). An existing
    ``directory`` is replaced only with ``replace`` (a run's own model); otherwise refused."""
    from safetensors.torch import save_file

    directory = Path(directory)
    if directory.exists() and not replace:
        raise ModelError(f"{directory} exists already; choose another directory or move it away")
    directory.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=directory.parent, prefix=f".{directory.name}.", suffix=".tmp"))
    try:
        tensors = {k: v.detach().to("cpu").contiguous() for k, v in weights.items()}
        save_file(tensors, str(tmp / WEIGHTS), metadata={"format": FORMAT})
        (tmp / META).write_text(json.dumps(_finite(dict(meta)), indent=1, allow_nan=False))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp's 0700 would keep a shared model from its readers
        for f in (WEIGHTS, META):
            os.chmod(tmp / f, 0o666 & ~umask)
        old = None
        if directory.exists():
            old = directory.with_name(f".{directory.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(directory, old)
        os.replace(tmp, directory)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return directory


def update_model_meta(directory: str | os.PathLike, **changes) -> Path:
    """Merge ``changes`` into a model's model.json (written, then renamed)."""
    path = Path(directory) / META
    meta = json.loads(path.read_text())
    meta.update(changes)
    tmp = path.with_name(META + ".tmp")
    tmp.write_text(json.dumps(_finite(meta), indent=1, allow_nan=False))
    os.replace(tmp, path)
    return path


def model_dir(spec: str | os.PathLike) -> Path:
    """The model directory that ``spec`` names: ``zoo:NAME``, a model directory, its
    model.json or model.safetensors, or a run directory holding ``model``."""
    text = str(spec)
    if text.startswith(ZOO_PREFIX):
        return zoo_path(text[len(ZOO_PREFIX):])
    path = Path(spec)
    if path.is_file() and path.name in (META, WEIGHTS):
        return path.parent
    if path.is_dir():
        if (path / META).exists() or (path / WEIGHTS).exists():
            return path
        if (path / "model" / META).exists():
            return path / "model"
        for old in (path / "checkpoints" / "last.pt", path / "last.pt"):
            if old.exists():
                raise ModelError(f"{path} holds a training checkpoint ({old.name}) but no model; write its model "
                                 f"with: python -m laserrl.model export {old}")
        raise ModelError(f"no model in {path}: expected {META} and {WEIGHTS}, or a run directory with model/")
    if path.is_file():
        if path.suffix == ".pt" or _is_torch_file(path):
            raise ModelError(f"{path} is a training checkpoint (torch format), not a model; laserrl reads models as "
                             f"safetensors + JSON. Write its model with: python -m laserrl.model export {path}")
        raise ModelError(f"{path} is not a laserrl model: give its directory (with {META} and {WEIGHTS}) or zoo:NAME")
    raise ModelError(f"model not found: {path}")


def record_dir(directory: str | os.PathLike) -> Path:
    """Where a model's training record lies (history.json, eval.json): the run directory of a
    run's ``model/``, or the directory of a zoo or stand-alone model itself."""
    directory = Path(directory)
    return directory.parent if directory.name == "model" else directory


def _is_torch_file(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            head = f.read(4)
        return head == b"PK\x03\x04" or head[:1] == b"\x80"  # torch's zip format, or a pickle (protocol >= 2)
    except OSError:
        return False


def read_meta(directory: Path) -> dict:
    path = directory / META
    if not path.is_file():
        raise ModelError(f"model {directory} has no {META}")
    if path.stat().st_size > MAX_META_BYTES:
        raise ModelError(f"{path} is {path.stat().st_size} bytes; a model.json is a few KB, refusing to read it")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ModelError(f"{path} is not valid JSON ({type(err).__name__}: {str(err).splitlines()[0]})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise ModelError(f"{path} is not a laserrl model (format {found!r}, expected {FORMAT!r})")
    config = meta.get("config")
    if not (isinstance(config, dict) and all(isinstance(config.get(k), dict) for k in ("env", "stage", "agent"))):
        raise ModelError(f"{path} lacks the training config (config.env, config.stage, config.agent)")
    stage = config["stage"]
    if not (isinstance(stage.get("controlled"), list) and isinstance(stage.get("steps_deg"), list)):
        raise ModelError(f"{path}: config.stage lacks its controlled angles and steps")
    n = meta.get("num_actions")
    if not isinstance(n, int) or isinstance(n, bool) or n != 3 ** len(stage["controlled"]):
        raise ModelError(f"{path}: num_actions {n!r} does not fit {len(stage['controlled'])} controlled angles")
    members = meta.get("ensemble", 1)
    if not isinstance(members, int) or isinstance(members, bool) or members < 1:
        raise ModelError(f"{path}: ensemble {members!r} is not a number of models")
    return meta


def read_weights(directory: Path) -> dict[str, torch.Tensor]:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = directory / WEIGHTS
    if not path.is_file():
        raise ModelError(f"model {directory} has no {WEIGHTS}")
    try:
        weights = load_file(str(path), device="cpu")
    except (SafetensorError, OSError, ValueError, RuntimeError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise ModelError(f"{path} is unreadable ({type(err).__name__}: {first})") from None
    bad = [k for k, v in weights.items() if not v.is_floating_point()]
    if bad or not weights:
        raise ModelError(f"{path} holds no Q-network (tensors {bad or 'none'})")
    return weights


def load_model(spec: str | os.PathLike) -> dict:
    """Read a model (see ``model_dir`` for what ``spec`` may be). Returns what a caller needs
    to rebuild and run it: ``qnet`` (tensors), ``config``, ``num_actions``, ``stage``,
    ``path`` (the model directory, or ``zoo:NAME``) and ``meta`` (all of model.json).
    Raises ``ModelError`` with one line for anything missing, malformed or foreign."""
    directory = model_dir(spec)
    meta = read_meta(directory)
    weights = read_weights(directory)
    shown = str(spec) if str(spec).startswith(ZOO_PREFIX) else str(directory)
    frames = meta.get("frames", (meta.get("card") or {}).get("frames"))
    return {"qnet": weights, "config": meta["config"], "num_actions": meta["num_actions"], "stage": meta.get("stage"),
            "frames": frames, "path": shown, "dir": str(directory), "meta": meta}


def ensemble_members(state: Mapping) -> list[dict[str, torch.Tensor]]:
    """The Q-network weights of each member of a loaded model (one for a plain model)."""
    count = int(state["meta"].get("ensemble", 1))
    if count == 1:
        return [dict(state["qnet"])]
    members: list[dict[str, torch.Tensor]] = [{} for _ in range(count)]
    for key, value in state["qnet"].items():
        prefix, _, rest = key.partition(".")
        index, _, name = rest.partition(".")
        if prefix != "members" or not index.isdigit() or int(index) >= count or not name:
            raise ModelError(f"{state['path']}: tensor {key!r} belongs to no member of the ensemble of {count}")
        members[int(index)][name] = value
    if not all(members):
        raise ModelError(f"{state['path']}: an ensemble of {count} with members missing")
    return members


def save_ensemble(out: str | os.PathLike, specs: list[str]) -> Path:
    """Write the ensemble of the models ``specs`` (each a model, see ``model_dir``) to ``out``;
    refuses an existing ``out``, models of different tasks or networks, and ensembles as members."""
    if len(specs) < 2:
        raise ModelError("an ensemble needs at least two models")
    states = [load_model(spec) for spec in specs]
    first = states[0]
    task = lambda st: (st["num_actions"], st["config"]["stage"].get("name"), st["config"]["stage"].get("K"),  # noqa: E731
                       st["config"]["agent"].get("network"), st["config"]["env"].get("physics"))
    for st in states:
        if st["meta"].get("ensemble", 1) != 1:
            raise ModelError(f"{st['path']} is an ensemble itself; give its members")
        if st["config"]["env"].get("gru_size") is not None:
            raise ModelError(f"{st['path']} is recurrent (env.gru_size): an ensemble averages feed-forward models")
        if task(st) != task(first):
            raise ModelError(f"{st['path']} is trained for another task or network than {first['path']} (stage, K, "
                             "actions, network and physics must agree)")
    weights = {f"members.{i}.{k}": v for i, st in enumerate(states) for k, v in st["qnet"].items()}
    cards = [st["meta"].get("card") or {} for st in states]
    card = {"command": " ; ".join(c.get("command") or "not recorded" for c in cards),
            **{key: cards[0].get(key) for key in ("commit", "laserrl_version", "machine", "date")},
            "frames": sum(int(st["frames"] or 0) for st in states),
            "episodes": sum(int(c.get("episodes") or 0) for c in cards),
            "train_seconds": round(sum(float(c.get("train_seconds") or 0) for c in cards), 1),
            "members": [{"model": st["path"], **c} for st, c in zip(states, cards)],
            "notes": f"the mean of the Q-values of {len(states)} models (laserrl.model ensemble)"}
    meta = model_metadata(first["config"], first["num_actions"], frames=card["frames"], ensemble=len(states),
                          card=card)
    return save_model(out, weights, meta)


def frames_since_scratch(state: Mapping) -> int | None:
    """Frames of a loaded model (``load_model``) together with those of the models it was
    warm-started from, back to the run that started from scratch (its card's
    ``frames_since_scratch``, written at training time); None where that is not known."""
    card = (state.get("meta") or {}).get("card") or {}
    if card.get("frames_since_scratch") is not None:
        return int(card["frames_since_scratch"])
    if not state["config"].get("init_from") and state.get("frames") is not None:
        return int(state["frames"])
    return None


def export_checkpoint(checkpoint: str | os.PathLike, out: str | os.PathLike | None = None) -> Path:
    """Write the model of a training checkpoint (``RUN/checkpoints/last.pt`` or ``best.pt``)
    into ``out`` (default: ``RUN/model``); refuses to overwrite. The checkpoint is read with
    ``torch.load(weights_only=True)``: a checkpoint holding pickled objects is refused (its
    message names ``python -m laserrl.checkpoint convert`` for files one made oneself). The
    weights exported are those a ``train.keep_best`` run kept, else the weight average of an
    ``agent.average_decay`` run, else the last ones."""
    state = load_checkpoint(checkpoint)
    ckpt = Path(state["path"])
    run = ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent
    out = Path(out) if out is not None else run / "model"
    weights = state.get("best_qnet") or state.get("averaged_qnet") or state["qnet"]
    meta = model_metadata(state["config"], state["num_actions"], frames=state.get("frames"),
                          exported_from=str(ckpt), checkpoint_format=CHECKPOINT_FORMAT)
    summary = run / "summary.json"
    if summary.exists():
        s = json.loads(summary.read_text())
        meta["card"] = {"frames": s.get("frames"), "train_seconds": s.get("train_seconds")}
        if s.get("best"):
            meta["best"] = s["best"]
    return save_model(out, weights, meta)


def main(argv: list[str] | None = None) -> int:
    """``python -m laserrl.model export CHECKPOINT [OUT]`` (``export_checkpoint``) and
    ``python -m laserrl.model ensemble OUT MODEL MODEL ...`` (``save_ensemble``)."""
    import argparse

    from laserrl.checkpoint import one_line_errors

    parser = argparse.ArgumentParser(prog="python -m laserrl.model")
    sub = parser.add_subparsers(dest="command", required=True)
    export = sub.add_parser("export", help="write the model (safetensors + JSON) of a training checkpoint")
    export.add_argument("path", help="RUN/checkpoints/last.pt (or the run directory)")
    export.add_argument("out", nargs="?", help="model directory to write (default: RUN/model)")
    ensemble = sub.add_parser("ensemble", help="write one model that acts on the mean Q-values of several models")
    ensemble.add_argument("out", help="model directory to write (must not exist)")
    ensemble.add_argument("models", nargs="+", help="the members: zoo:NAME, run or model directories")
    args = parser.parse_args(argv)
    if args.command == "ensemble":
        return one_line_errors(parser.prog, lambda: print(f"model: {save_ensemble(args.out, args.models)}"))
    return one_line_errors(parser.prog, lambda: print(f"model: {export_checkpoint(args.path, args.out)}"))


if __name__ == "__main__":
    raise SystemExit(main())
