"""The shareable model format (laserrl.model): safetensors + JSON, read without pickle; every
malformed or foreign file gets one line naming it."""
import json
import os
import pickle
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from laserrl.model import (FORMAT, META, WEIGHTS, ModelError, export_checkpoint, load_model, model_metadata,
                           save_model)
from laserrl.paths import CONF_DIR


def _config() -> dict:
    return {"env": OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "env" / "paper.yaml")),
            "stage": OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "stage" / "siso.yaml")),
            "agent": OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "agent" / "ddqn.yaml")), "seed": 0}


def _model(tmp_path: Path) -> tuple[Path, dict]:
    from laserrl.agents.dqn import make_qnet

    net = _config()["agent"]["network"]
    qnet = make_qnet(3, 256, net["channels"], net["kernel_size"], net["pool"], net["hidden"], net["negative_slope"])
    weights = qnet.state_dict()
    return save_model(tmp_path / "m", weights, model_metadata(_config(), 3, frames=128)), weights


def test_round_trip_keeps_every_tensor_and_the_metadata(tmp_path):
    directory, weights = _model(tmp_path)
    state = load_model(directory)
    assert set(state["qnet"]) == set(weights)
    assert all(torch.equal(state["qnet"][k], weights[k]) for k in weights)
    assert state["num_actions"] == 3 and state["stage"] == "siso" and state["frames"] == 128
    assert state["meta"]["format"] == FORMAT and state["meta"]["actions"]["controlled"] == ["alpha1"]
    for spec in (directory / META, directory / WEIGHTS, directory.parent / "m"):  # the files or the directory
        assert load_model(spec)["dir"] == str(directory)
    # a run directory names its model/
    run = tmp_path / "run"
    run.mkdir()
    os.replace(directory, run / "model")
    assert load_model(run)["dir"] == str(run / "model")


def test_save_refuses_to_overwrite_unless_asked(tmp_path):
    directory, weights = _model(tmp_path)
    before = (directory / WEIGHTS).read_bytes()
    with pytest.raises(ModelError, match="exists already"):
        save_model(directory, weights, model_metadata(_config(), 3))
    assert (directory / WEIGHTS).read_bytes() == before
    save_model(directory, {k: v + 1 for k, v in weights.items()}, model_metadata(_config(), 3), replace=True)
    assert (directory / WEIGHTS).read_bytes() != before
    assert not [p for p in directory.parent.iterdir() if p.name.startswith(".")]  # no leftovers


def _broken(tmp_path: Path, name: str, make) -> Path:
    directory, _ = _model(tmp_path / name)
    make(directory)
    return directory


MALFORMED = {
    "truncated weights": (lambda d: (d / WEIGHTS).write_bytes((d / WEIGHTS).read_bytes()[:1000]), "is unreadable"),
    "empty weights": (lambda d: (d / WEIGHTS).write_bytes(b""), "is unreadable"),
    "text as weights": (lambda d: (d / WEIGHTS).write_text("hello"), "is unreadable"),
    "huge header length": (lambda d: (d / WEIGHTS).write_bytes((2**62).to_bytes(8, "little") + b"{}"), "is unreadable"),
    "integer tensors": (lambda d: __import__("safetensors.torch").torch.save_file({"w": torch.ones(2, dtype=torch.int64)},
                                                                                   str(d / WEIGHTS)), "holds no Q-network"),
    "no weights": (lambda d: (d / WEIGHTS).unlink(), "has no model.safetensors"),
    "no metadata": (lambda d: (d / META).unlink(), "has no model.json"),
    "invalid JSON": (lambda d: (d / META).write_text("{not json"), "is not valid JSON"),
    "binary JSON": (lambda d: (d / META).write_bytes(b"\xff\xfe\x00"), "is not valid JSON"),
    "JSON list": (lambda d: (d / META).write_text("[1, 2]"), "is not a laserrl model"),
    "other format": (lambda d: (d / META).write_text('{"format": "something-else"}'), "is not a laserrl model"),
    "no config": (lambda d: (d / META).write_text(json.dumps({"format": FORMAT, "num_actions": 3})),
                  "lacks the training config"),
    "head does not fit": (lambda d: (d / META).write_text(json.dumps({**json.loads((d / META).read_text()),
                                                                      "num_actions": 9})), "does not fit"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_a_malformed_model_gets_one_line(tmp_path, case):
    make, message = MALFORMED[case]
    directory = _broken(tmp_path, "x", make)
    with pytest.raises(ModelError, match=message) as info:
        load_model(directory)
    assert "\n" not in str(info.value) and str(directory) in str(info.value)


def test_torch_files_and_unknown_paths_are_refused_before_reading(tmp_path):
    marker = tmp_path / "payload-ran"

    class Payload:
        def __reduce__(self):
            return os.system, (f"touch {marker}",)

    run = tmp_path / "run" / "checkpoints"
    run.mkdir(parents=True)
    torch.save({"w": Payload()}, run / "last.pt")
    with open(tmp_path / "weights.bin", "wb") as f:
        pickle.dump(Payload(), f)
    with pytest.raises(ModelError, match=r"training checkpoint .*python -m laserrl.model export"):
        load_model(run / "last.pt")
    with pytest.raises(ModelError, match=r"holds a training checkpoint .*export"):
        load_model(tmp_path / "run")
    with pytest.raises(ModelError, match="training checkpoint"):
        load_model(tmp_path / "weights.bin")  # a legacy pickle
    with pytest.raises(ModelError, match="model not found"):
        load_model(tmp_path / "nothing")
    with pytest.raises(ModelError, match="no such model in the zoo; models: "):
        load_model("zoo:no-such-model")
    with pytest.raises(ModelError, match="no such model in the zoo"):
        load_model("zoo:../../etc")
    assert not marker.exists()


def test_export_writes_the_model_of_a_checkpoint_and_refuses_to_overwrite(tmp_path):
    from laserrl.model import main as model_main

    _, weights = _model(tmp_path)
    ckpt = tmp_path / "run" / "checkpoints" / "last.pt"
    ckpt.parent.mkdir(parents=True)
    torch.save({"format": "laserrl-checkpoint-1", "qnet": weights, "config": _config(), "num_actions": 3,
                "frames": 64}, ckpt)
    assert model_main(["export", str(ckpt)]) == 0
    state = load_model(tmp_path / "run")
    assert all(torch.equal(state["qnet"][k], weights[k]) for k in weights) and state["frames"] == 64
    assert model_main(["export", str(ckpt)]) == 2  # RUN/model exists: nothing overwritten
    with pytest.raises(ModelError, match="exists already"):
        export_checkpoint(ckpt)


def _members(tmp_path: Path, count: int = 2) -> list[Path]:
    from laserrl.agents.dqn import make_qnet

    net = _config()["agent"]["network"]
    out = []
    for i in range(count):
        torch.manual_seed(i)
        qnet = make_qnet(3, 256, net["channels"], net["kernel_size"], net["pool"], net["hidden"], net["negative_slope"])
        card = {"command": f"laserrl-train seed={i}", "frames": 128, "episodes": 6, "train_seconds": 10.0}
        out.append(save_model(tmp_path / f"m{i}", qnet.state_dict(), model_metadata(_config(), 3, frames=128, card=card)))
    return out


def test_an_ensemble_acts_on_the_mean_q_of_its_members(tmp_path):
    from torchrl.data import Categorical

    from laserrl.evaluate import load_qnet
    from laserrl.model import main, save_ensemble

    members = _members(tmp_path)
    assert main(["ensemble", str(tmp_path / "ens"), *map(str, members)]) == 0
    state = load_model(tmp_path / "ens")
    assert state["meta"]["ensemble"] == 2 and state["frames"] == 256
    card = state["meta"]["card"]
    assert card["command"] == "laserrl-train seed=0 ; laserrl-train seed=1" and card["train_seconds"] == 20.0
    fields, angles = torch.randn(5, 4, 256), torch.randn(5, 4)
    with torch.no_grad():
        q = load_qnet(state, Categorical(3))(fields, angles)
        singles = [load_qnet(load_model(m), Categorical(3))(fields, angles) for m in members]
    torch.testing.assert_close(q, (singles[0] + singles[1]) / 2)
    assert not torch.allclose(singles[0], singles[1])
    # refused: an existing directory, a single model, an ensemble as a member, another task
    with pytest.raises(ModelError, match="exists already"):
        save_ensemble(tmp_path / "ens", members)
    with pytest.raises(ModelError, match="at least two"):
        save_ensemble(tmp_path / "one", members[:1])
    with pytest.raises(ModelError, match="is an ensemble itself"):
        save_ensemble(tmp_path / "nested", [tmp_path / "ens", members[0]])
    meta = json.loads((members[1] / META).read_text())
    meta["config"]["stage"]["K"] = 0.3
    (members[1] / META).write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="another task or network"):
        save_ensemble(tmp_path / "mixed", members)
    meta["config"]["stage"]["K"] = 0.1
    meta["config"]["env"]["gru_size"] = 16  # a recurrent model keeps a state the others do not share
    (members[1] / META).write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="is recurrent"):
        save_ensemble(tmp_path / "recurrent", members)
    assert not (tmp_path / "recurrent").exists()


def test_an_ensemble_with_a_stray_tensor_or_a_bad_count_is_refused(tmp_path):
    from laserrl.model import save_ensemble

    ens = save_ensemble(tmp_path / "ens", _members(tmp_path))
    from laserrl.model import ensemble_members

    meta = json.loads((ens / META).read_text())
    meta["ensemble"] = 3  # more members than the weights hold
    (ens / META).write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="members missing"):
        ensemble_members(load_model(ens))
    meta["ensemble"] = "two"
    (ens / META).write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="ensemble 'two'"):
        load_model(ens)


def test_warm_starting_from_an_ensemble_is_refused(tmp_path):
    from laserrl.agents.dqn import make_qnet
    from laserrl.model import save_ensemble
    from laserrl.warmstart import warm_start

    ens = save_ensemble(tmp_path / "ens", _members(tmp_path))
    net = _config()["agent"]["network"]
    qnet = make_qnet(3, 256, net["channels"], net["kernel_size"], net["pool"], net["hidden"], net["negative_slope"])
    with pytest.raises(Exception, match="is an ensemble of 2 models; warm-start from one of its members"):
        warm_start(qnet, str(ens), ["alpha1"])


def test_the_commit_is_read_once_per_process(monkeypatch):
    """A model card names the commit the run started with, not one made while it trained."""
    import subprocess

    from laserrl import model

    model.git_commit.cache_clear()
    calls = []
    real = subprocess.run

    def counting(*args, **kwargs):
        calls.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(subprocess, "run", counting)
    first = model.git_commit()
    n = len(calls)
    assert model.git_commit() == first and len(calls) == n
    model.git_commit.cache_clear()
