"""Checkpoints: one file per run state, written atomically (write, then rename)."""
from __future__ import annotations

import json
import os
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
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # truncated or foreign files fail in many ways inside torch
        raise CheckpointError(f"checkpoint {path} is unreadable ({type(err).__name__}: {err})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a laserrl checkpoint")
    for key in ("qnet", "config", "num_actions"):
        if key not in state:
            raise CheckpointError(f"checkpoint {path} lacks '{key}'")
    state["path"] = str(path)
    return state
