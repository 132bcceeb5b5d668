"""A checkpoint from someone else cannot run code: a pickle whose payload calls a function is
refused by every entry point that takes a checkpoint, with one line, and the payload never runs."""
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from laserrl.checkpoint import CheckpointError, convert_checkpoint, load_checkpoint


class _Payload:
    """Unpickling this calls os.system, which would create ``marker``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _evil(tmp_path: Path) -> tuple[Path, Path]:
    marker = tmp_path / "payload-ran"
    path = tmp_path / "evil" / "checkpoints" / "last.pt"
    path.parent.mkdir(parents=True)
    # the shape of a laserrl checkpoint, with the payload where a tensor would be
    torch.save({"format": "laserrl-checkpoint-1", "qnet": {"w": _Payload(marker)}, "config": {}, "num_actions": 3},
               path)
    with open(tmp_path / "evil.pkl", "wb") as f:  # a plain pickle, not torch's zip format
        pickle.dump(_Payload(marker), f)
    return path, marker


def test_load_checkpoint_refuses_pickled_calls(tmp_path):
    path, marker = _evil(tmp_path)
    for candidate in (path, tmp_path / "evil.pkl"):
        with pytest.raises(CheckpointError) as info:
            load_checkpoint(candidate)
        assert str(info.value).startswith(f"checkpoint {candidate} ") and "\n" not in str(info.value)
    assert not marker.exists()


def test_a_harmless_malformed_file_gets_one_line(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(CheckpointError, match=r"is unreadable") as info:
        load_checkpoint(bad)
    assert "\n" not in str(info.value)
    torch.save({"format": "laserrl-checkpoint-1", "config": {}}, tmp_path / "partial.pt")
    with pytest.raises(CheckpointError, match="lacks 'qnet'"):
        load_checkpoint(tmp_path / "partial.pt")


def test_convert_keeps_the_original_and_refuses_to_overwrite(tmp_path):
    import numpy as np

    path = tmp_path / "old.pt"
    torch.save({"format": "laserrl-checkpoint-1", "qnet": {}, "config": {}, "num_actions": 3,
                "resume": {"rng": {"numpy": np.random.get_state()}}}, path)
    with pytest.raises(CheckpointError, match=r"python -m laserrl.checkpoint convert"):
        load_checkpoint(path)
    convert_checkpoint(path)
    state = load_checkpoint(path)
    assert state["resume"]["rng"]["numpy"]["kind"] == "MT19937"
    assert (tmp_path / "old.pt.pickled").exists()
    with pytest.raises(CheckpointError, match="exists already"):
        convert_checkpoint(path)


@pytest.mark.parametrize("command, args", [
    ("laserrl-eval", ["checkpoint={ckpt}"]),
    ("laserrl-control", ["controller=rl", "scenario=constant", "checkpoint={ckpt}", "num_cavities=1", "scenario.steps=2"]),
    ("laserrl-train", ["experiment=smoke", "init_from={ckpt}"]),
    ("laserrl-train", ["resume={run}"]),
])
def test_every_entry_point_refuses_the_payload_with_one_line(tmp_path, command, args):
    path, marker = _evil(tmp_path)
    exe = Path(sys.executable).parent / command
    args = [a.format(ckpt=path, run=path.parent.parent) for a in args]
    res = subprocess.run([str(exe), *args, f"hydra.run.dir={tmp_path / 'out'}"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode != 0 and "Traceback" not in res.stderr, res.stderr[-2000:]
    errors = [line for line in res.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and "holds pickled objects" in errors[0], res.stderr[-2000:]
    assert not marker.exists()
