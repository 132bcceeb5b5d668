"""Sweep configs (laserrl/conf/sweep, also reachable as sweeps/ in a checkout): they compose,
sweep real config keys, and run with -m (Optuna, seeds) and with Hydra's joblib and submitit launchers."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir

from laserrl.train import check_train_config
from laserrl.paths import CONF_DIR

ROOT = Path(__file__).resolve().parent.parent
CONF = Path(CONF_DIR)
SWEEPS = CONF / "sweep"
WANDB_SWEEPS = sorted(SWEEPS.glob("wandb/*.yaml"))
SMOKE = ["experiment=smoke", "env.physics.n=64", "env.physics.z_steps=2", "train.progress=false"]


def _compose(overrides, hydra=False):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=overrides, return_hydra_config=hydra)


def _sample(spec: str):
    """A value inside a Hydra sweep expression such as tag(log, interval(1e-4, 3e-3)), range(0, 5) or choice(1, 3)."""
    inner = spec[spec.rindex("(") + 1: spec.index(")")]
    low = float(inner.split(",")[0])
    return int(low) if spec.startswith(("int(", "range(")) or (spec.startswith("choice(") and low.is_integer()) else low


def test_the_checkouts_sweeps_folder_is_the_packaged_sweep_group():
    assert (ROOT / "sweeps").resolve() == SWEEPS.resolve()


def test_the_wandb_sweep_the_readme_names_exists():
    assert [p.name for p in WANDB_SWEEPS] == ["ddqn.yaml"]


@pytest.mark.parametrize("name", sorted(p.stem for p in SWEEPS.glob("*.yaml")))
def test_hydra_sweeps_compose_and_sweep_real_keys(name):
    cfg = _compose([f"sweep={name}"], hydra=True)
    params = dict(cfg.hydra.sweeper.params)
    assert params, f"sweeps/{name}.yaml sweeps nothing"
    # every swept key exists and accepts a value from its range
    swept = _compose([f"{key}={_sample(spec)}" for key, spec in params.items()])
    check_train_config(swept)


def test_optuna_sweep_maximises_the_returned_metric():
    cfg = _compose(["sweep=optuna"], hydra=True)
    assert cfg.hydra.sweeper._target_.endswith("OptunaSweeper")
    assert cfg.hydra.sweeper.direction == "maximize" and cfg.metric == "eval/mean_final_reward"
    assert cfg.hydra.sweeper.storage is None  # in-memory: optuna < 3 with sqlalchemy 2


@pytest.mark.parametrize("path", WANDB_SWEEPS or [SWEEPS / "wandb" / "ddqn.yaml"])
def test_wandb_sweeps_drive_the_hydra_app(path):
    spec = yaml.safe_load(path.read_text())
    assert "${args_no_hyphens}" in spec["command"] and spec["program"] == "laserrl-train"
    assert spec["metric"]["name"] in ("eval/mean_final_reward", "eval/success_rate")
    values = [f"{key}={p['values'][-1] if 'values' in p else p.get('min', p.get('value'))}"
              for key, p in spec["parameters"].items()]
    check_train_config(_compose(values))


def _multirun(tmp_path, *args):
    exe = Path(sys.executable).parent / "laserrl-train"
    res = subprocess.run([str(exe), "-m", *SMOKE, f"hydra.sweep.dir={tmp_path}", *args], cwd=tmp_path,
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    return res


def test_optuna_sweep_runs_locally(tmp_path):
    _multirun(tmp_path, "sweep=optuna", "hydra.sweeper.n_trials=2")
    result = yaml.safe_load((tmp_path / "optimization_results.yaml").read_text())
    assert set(result["best_params"]) == {"optim.lr", "agent.gamma", "agent.exploration.decay_frames",
                                          "agent.target.tau", "replay.alpha", "replay.beta", "agent.n_steps"}
    trials = sorted(p for p in tmp_path.iterdir() if p.is_dir() and p.name.isdigit())
    assert [p.name for p in trials] == ["0", "1"]
    # the best value is the largest metric that the trials' main returned
    returned = [json.loads((p / "summary.json").read_text())["eval/mean_final_reward"] for p in trials]
    assert result["best_value"] == pytest.approx(max(returned))


def test_seed_sweep_runs_each_seed_side_by_side_with_the_joblib_launcher(tmp_path):
    # the command line narrows the sweep; joblib runs the seeds at once, one torch thread each
    # (docs/benchmarks.md, the training loop)
    _multirun(tmp_path, "sweep=seeds", "seed=range(0,2)", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
              "threads=1")
    for i in range(2):
        assert (tmp_path / str(i) / "checkpoints" / "last.pt").exists()
        assert json.loads((tmp_path / str(i) / "summary.json").read_text())["frames"] == 64
        assert f"seed: {i}" in (tmp_path / str(i) / ".hydra" / "overrides.yaml").read_text().replace("=", ": ")


def test_submitit_local_launcher(tmp_path):
    # the same launcher family that submits to SLURM (hydra/launcher=submitit_slurm)
    _multirun(tmp_path, "hydra/launcher=submitit_local", "seed=3", "hydra.launcher.timeout_min=10")
    assert (tmp_path / "0" / "checkpoints" / "last.pt").exists()
    assert (tmp_path / "0" / "eval.json").exists()
    assert list((tmp_path / ".submitit").glob("*/*_result.pkl"))

