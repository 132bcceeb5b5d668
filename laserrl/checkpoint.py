"""Checkpoints: one file per run state, written atomically (write, then rename)."""
from __future__ import annotations

import json
import os
import pickle
import re
import tempfile
from pathlib import Path
from typing import Any

import torch

FORMAT = "laserrl-checkpoint-1"


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable or does not fit the requested use."""


def save_checkpoint(state: dict[str, Any], path: str | os.PathLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    os.close(fd)
    try:
        torch.save({"format": FORMAT, **state}, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def save_json(obj: Any, path: str | os.PathLike, indent: int | None = None) -> Path:
    """Write ``obj`` as JSON atomically (write, then rename): readers see the old file or the new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=indent))
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    path = Path(path)
    if path.is_dir():
        candidates = [c for c in (path / "checkpoints" / "last.pt", path / "last.pt") if c.exists()]
        if not candidates:
            raise CheckpointError(f"checkpoint not found: no checkpoints/last.pt in {path}")
        path = candidates[0]
    if not path.exists():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        # weights_only: tensors and plain data only; a pickled object or call is refused, never run
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        found = re.search(r"Unsupported global: GLOBAL (\S+)", str(err))
        what = f" ({found.group(1)})" if found else ""
        raise CheckpointError(f"checkpoint {path} holds pickled objects{what}, not only tensors and plain data; "
                              "laserrl does not load such files (they can run code). If you made it yourself with "
                              f"an older laserrl: python -m laserrl.checkpoint convert {path}") from None
    except Exception as err:  # truncated or foreign files fail in many ways inside torch
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise CheckpointError(f"checkpoint {path} is unreadable ({type(err).__name__}: {first})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a laserrl checkpoint")
    for key in ("qnet", "config", "num_actions"):
        if key not in state:
            raise CheckpointError(f"checkpoint {path} lacks '{key}'")
    state["path"] = str(path)
    return state


def convert_checkpoint(path: str | os.PathLike) -> Path:
    """Rewrite a checkpoint of an older laserrl, whose numpy RNG state was pickled, as tensors and
    plain data. This unpickles the file, which can run code: only for files you made yourself.
    The original is kept as ``PATH.pickled``."""
    path = Path(path)
    kept = path.with_name(path.name + ".pickled")
    if kept.exists():
        raise CheckpointError(f"{kept} exists already; move it away first")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)  # trusted by the caller
    except Exception as err:
        raise CheckpointError(f"checkpoint {path} is unreadable ({type(err).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a laserrl checkpoint")
    rng = (state.get("resume") or {}).get("rng") or {}
    if isinstance(rng.get("numpy"), tuple):
        import numpy as np

        kind, keys, pos, has_gauss, cached = rng["numpy"]
        rng["numpy"] = {"kind": str(kind), "keys": torch.from_numpy(np.asarray(keys).astype(np.int64)),
                        "pos": int(pos), "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}
    os.replace(path, kept)
    state.pop("format", None)
    save_checkpoint(state, path)
    torch.load(path, map_location="cpu", weights_only=True)  # what load_checkpoint will read
    return path


def one_line_errors(prog: str, command) -> int:
    """Run ``command()`` for a small command-line tool: 0, or 2 after one line on stderr for a
    CheckpointError (a ModelError) or OSError. A reader that stops early (``| head``, ``| grep -q``)
    is not an error: the rest of the output is dropped."""
    import os
    import sys

    try:
        command()
        sys.stdout.flush()
    except BrokenPipeError:
        # Python's documented way out: point stdout at devnull so that its flush at exit is quiet
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (CheckpointError, OSError) as err:
        print(f"{prog}: error: {err}".splitlines()[0], file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m laserrl.checkpoint convert PATH``: see ``convert_checkpoint``. (The model of
    a checkpoint, to share: ``python -m laserrl.model export PATH``.)"""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m laserrl.checkpoint")
    sub = parser.add_subparsers(dest="command", required=True)
    convert = sub.add_parser("convert", help="rewrite an older checkpoint you made yourself as tensors and plain data")
    convert.add_argument("path")
    args = parser.parse_args(argv)
    return one_line_errors(parser.prog, lambda: print(f"converted: {convert_checkpoint(args.path)} "
                                                      f"(original kept as {args.path}.pickled)"))


if __name__ == "__main__":
    raise SystemExit(main())
