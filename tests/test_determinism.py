"""The same seed gives the same training run on CPU (issue: reliability)."""
import json
import subprocess
import sys
from pathlib import Path

import torch

SMOKE = ["experiment=smoke", "env.physics.n=64", "env.physics.z_steps=2", "train.total_frames=128"]


def _start(tmp_path, name, *args):
    exe = Path(sys.executable).parent / "laserrl-train"
    out = tmp_path / name
    proc = subprocess.Popen([str(exe), *SMOKE, *args, f"hydra.run.dir={out}"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    return proc, out


def _result(proc, out):
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-2000:]
    history = [{k: v for k, v in h.items() if not k.startswith("time")}
               for h in json.loads((out / "history.json").read_text())]
    return history, torch.load(out / "checkpoints" / "last.pt", weights_only=False)["qnet"]


def test_same_seed_same_run_other_seed_other_run(tmp_path):
    # three separate processes at once (each is mostly start-up): nothing is shared between them
    runs = [_start(tmp_path, name, f"seed={seed}") for name, seed in (("a", 5), ("b", 5), ("c", 6))]
    (h1, w1), (h2, w2), (h3, w3) = (_result(*run) for run in runs)
    assert h1 == h2  # rewards, losses, epsilon: every logged number
    assert all(torch.equal(w1[k], w2[k]) for k in w1)
    assert h1 != h3 and not all(torch.equal(w1[k], w3[k]) for k in w1)


def test_validations_and_reselection_do_not_change_what_is_learned(tmp_path):
    # train.keep_best / train.reselect evaluate on generators of their own: the same seed learns the same weights
    runs = [_start(tmp_path, "plain", "seed=5"),
            _start(tmp_path, "validated", "seed=5", "train.keep_best=true", "train.eval_every_frames=32",
                   "train.reselect={top:2,repeats:1}")]
    (h1, w1), (h2, w2) = (_result(*run) for run in runs)
    assert any("eval/success_rate" in h for h in h2)
    assert h1 == [{k: v for k, v in h.items() if not k.startswith("eval/")} for h in h2]
    assert all(torch.equal(w1[k], w2[k]) for k in w1)
