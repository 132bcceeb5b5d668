"""A checkpoint or model from someone else cannot run code: a pickle whose payload calls a
function, as a torch checkpoint or posing as a model's safetensors, is refused by every entry
point that takes one, with one line, and the payload never runs."""
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


def _evil_model(tmp_path: Path) -> tuple[Path, Path]:
    """A run directory whose model/ looks right, with a pickle payload as model.safetensors."""
    marker = tmp_path / "payload-ran"
    model = tmp_path / "evil-run" / "model"
    model.mkdir(parents=True)
    with open(model / "model.safetensors", "wb") as f:
        pickle.dump(_Payload(marker), f)
    (model / "model.json").write_text('{"format": "laserrl-model-1", "num_actions": 3, "config": {"env": {}, '
                                      '"agent": {}, "stage": {"controlled": ["alpha1"], "steps_deg": [2.0]}}}')
    return model.parent, marker


ENTRY_POINTS = [
    ("laserrl-eval", ["checkpoint={model}"]),
    ("laserrl-control", ["controller=rl", "scenario=constant", "checkpoint={model}", "num_cavities=1", "scenario.steps=2"]),
    ("laserrl-train", ["experiment=smoke", "init_from={model}"]),
]


def _run(command: str, args: list[str], tmp_path: Path) -> list[str]:
    exe = Path(sys.executable).parent / command
    res = subprocess.run([str(exe), *args, f"hydra.run.dir={tmp_path / 'out'}"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode != 0 and "Traceback" not in res.stderr, res.stderr[-2000:]
    errors = [line for line in res.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1, res.stderr[-2000:]
    return errors


@pytest.mark.parametrize("command, args", ENTRY_POINTS + [("laserrl-train", ["resume={run}"])])
def test_every_entry_point_refuses_a_pickled_checkpoint_with_one_line(tmp_path, command, args):
    """Models are read as safetensors + JSON: a torch checkpoint given as a model is refused
    before it is opened (with the export command); resume= reads it with weights_only."""
    path, marker = _evil(tmp_path)
    errors = _run(command, [a.format(model=path, run=path.parent.parent) for a in args], tmp_path)
    expected = "holds pickled objects" if "resume" in args[0] else "python -m laserrl.model export"
    assert expected in errors[0], errors
    assert not marker.exists()


@pytest.mark.parametrize("command, args", ENTRY_POINTS)
def test_every_entry_point_refuses_a_pickle_posing_as_a_model(tmp_path, command, args):
    run, marker = _evil_model(tmp_path)
    errors = _run(command, [a.format(model=run) for a in args], tmp_path)
    assert "model.safetensors is unreadable" in errors[0], errors
    assert not marker.exists()


def test_resume_refuses_a_replay_buffer_holding_a_pickle(tmp_path):
    """TorchRL's replay loader unpickles a prefetch queue (and non-tensor fields) if present;
    laserrl writes none and refuses to resume from a buffer that holds one."""
    from laserrl.resume import load_run

    marker = tmp_path / "payload-ran"
    ckpt = tmp_path / "run" / "checkpoints" / "last.pt"
    replay = ckpt.parent / "replay-0000000064"
    replay.mkdir(parents=True)
    (replay / "buffer_metadata.json").write_text("{}")
    with open(replay / "prefetch.pkl", "wb") as f:
        pickle.dump(_Payload(marker), f)
    torch.save({"format": "laserrl-checkpoint-1", "qnet": {}, "config": {}, "num_actions": 3, "frames": 64,
                "replay": replay.name, "resume": {}}, ckpt)
    with pytest.raises(CheckpointError, match=r"holds prefetch.pkl, which laserrl does not load") as info:
        load_run(tmp_path / "run")
    assert "\n" not in str(info.value) and not marker.exists()


def test_a_saved_replay_buffer_holds_only_arrays_and_json(tmp_path):
    from laserrl.agents.dqn import make_replay
    from laserrl.resume import REPLAY_SUFFIXES, RunSaver
    from tensordict import TensorDict

    replay = make_replay("prioritized", 16, 4, 0.6, 0.4)
    replay.extend(TensorDict(obs=torch.zeros(8, 3), batch_size=[8]))
    saver = RunSaver(tmp_path, replay)
    saver.save({"frames": 8, "qnet": {}, "config": {}, "num_actions": 3})
    files = [p for p in (tmp_path / "checkpoints").rglob("*") if p.is_file() and p.name != "last.pt"]
    assert files and all(p.suffix in REPLAY_SUFFIXES for p in files), sorted({p.name for p in files})
