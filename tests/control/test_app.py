"""laserrl-control: every new config composes and builds; hostile values give one clear
error before any simulation; the real entry point runs all controllers with a DQN trained
here (tiny) and writes control.json, the table and the figure."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from laserrl.config import ConfigError
from laserrl.control import Scenario
from laserrl.control.app import ALL, build_controller, run_control, sweep_metric
from laserrl.paths import CONF_DIR

CONF = Path(CONF_DIR)
CONTROLLERS = sorted(p.stem for p in (CONF / "controller").glob("*.yaml"))
SCENARIOS = sorted(p.stem for p in (CONF / "scenario").glob("*.yaml"))
SMOKE_PHYSICS = ["env.physics.n=64", "env.physics.z_steps=2", "env.max_round_trips=5", "env.compile=false"]


def _compose(overrides, name="control"):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny DQN (siso, alpha1) trained with the smoke settings."""
    from laserrl.train import train

    out = tmp_path_factory.mktemp("dqn")
    cfg = _compose(["experiment=smoke", *SMOKE_PHYSICS[:2], f"run_dir={out}", "train.progress=false",
                    "eval.plots=false"], name="config")
    train(cfg)
    return out / "model"


def test_controller_groups():
    assert set(CONTROLLERS) == {*ALL, "all"}


@pytest.mark.parametrize("controller", CONTROLLERS)
def test_every_controller_config_composes_and_builds(controller):
    cfg = _compose([f"controller={controller}"])
    assert cfg.controller.name == controller
    ccfg = OmegaConf.to_container(cfg.controller, resolve=True)
    for name in (ALL if controller == "all" else [controller]):
        sub = ccfg[name] if controller == "all" else ccfg
        policy = (lambda td: td) if name in ("rl", "hybrid") else None
        c = build_controller(name, sub, ["alpha1", "alpha2"], 2, 0, policy, [2.0, 2.0])
        assert c.name == name


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_every_scenario_config_composes_and_builds(scenario):
    cfg = _compose([f"scenario={scenario}"])
    assert Scenario(**OmegaConf.to_container(cfg.scenario, resolve=True)).name == scenario


def _run(overrides, tmp_path):
    return run_control(_compose(["scenario=constant", *SMOKE_PHYSICS, "num_cavities=2", "scenario.steps=4", "plots=false",
                                 f"run_dir={tmp_path}", *overrides]))


@pytest.mark.parametrize("overrides, match", [
    (["controller=esc", "controller.gain=-1"], "controller: gain"),
    (["controller=esc", "controller.frequency.alpha2=0.125", "controlled=[alpha1,alpha2]"], "controller: frequency"),
    (["controller=ga", "controller.elite=9"], "elite"),
    (["controller=hybrid"], "checkpoint=MODEL"),
    (["controller=esc", "num_cavities=0"], "num_cavities"),
    (["controller=esc", "controlled=[alpha7]"], "controlled"),
    (["controller=esc", "metric=speed"], "metric"),
    (["controller=esc", "scenario.jumps.times=[9]"], "scenario.jumps.times"),
    (["controller=esc", "plates.noise_deg=-1"], "plates.noise_deg"),
    (["controller=esc", "physics_spread=0.9"], "physics_spread"),
    (["controller=esc", "plates.backlash_deg=.nan"], "plates.backlash_deg"),
    (["controller=esc", "+plates.friction=1"], "plates: .*friction"),
    (["controller=all", "controller.only=[esc,bogus]"], "controller.only"),
    (["controller=all", "controller.only=[esc,esc]"], "controller.only"),
    (["controller=all", "controller.only=[esc,ga]"], "metric_controller"),
])
def test_hostile_values_fail_before_simulating(overrides, match, tmp_path):
    with pytest.raises(ValueError, match=match):
        _run(overrides, tmp_path)
    assert not (tmp_path / "control.json").exists()


@pytest.mark.parametrize("overrides, match", [
    (["controller=rl", "controlled=[alpha2]"], "differs"),
    (["controller=hybrid", "controller.unlock_r=0.3"], "controller: unlock_r"),
    (["controller=hybrid", "controller.settle_rise=-0.1"], "controller: settle_rise"),
    (["controller=all", "controller.hybrid.esc.lowpass_cutoff=0.7"], "controller.hybrid.esc: lowpass_cutoff"),
    (["controller=all", "metric_controller=best"], "metric_controller"),
    (["controller=rl", "rl_steps_deg=0"], "rl_steps_deg"),
    (["controller=rl", "rl_steps_deg=[1.0,2.0]"], "rl_steps_deg"),  # the checkpoint controls one angle
    (["controller=rl", "rl_steps_deg=nan"], "rl_steps_deg"),
    (["controller=rl", "rl_fine_from_r=0.4"], "give rl_steps_deg too"),
    (["controller=rl", "rl_steps_deg=1.0", "rl_fine_from_r=-1"], "rl_fine_from_r"),
])
def test_hostile_values_with_a_checkpoint(checkpoint, overrides, match, tmp_path):
    with pytest.raises(ConfigError, match=match):
        _run([*overrides, f"checkpoint={checkpoint}"], tmp_path)
    assert not (tmp_path / "control.json").exists()


def test_entry_point_runs_every_controller(checkpoint, tmp_path):
    steps, jump = 10, 5
    exe = Path(sys.executable).parent / "laserrl-control"
    res = subprocess.run([str(exe), "controller=all", "scenario=drift_jumps", f"checkpoint={checkpoint}", "num_cavities=2",
                          f"scenario.steps={steps}", f"scenario.jumps.times=[{jump}]", "compile=false",
                          "controller.hybrid.lock_r=0.2", f"hydra.run.dir={tmp_path}"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"control: {tmp_path / 'control.json'}" in res.stdout
    out = json.loads((tmp_path / "control.json").read_text())
    assert out["controllers"] == list(ALL) and out["controlled"] == ["alpha1"]
    assert set(out["controller_settings"]) == set(ALL)  # the settings each controller ran with
    assert out["controller_settings"]["hybrid"]["lock_r"] == 0.2 and out["controller_settings"]["hybrid"]["esc"]["gain"] > 0
    assert out["env"]["max_round_trips"] == 5 and out["env"]["physics"]["n"] == 64  # the checkpoint's per-step physics
    K = out["K"]
    assert len(K) == 2 and len(K[0]) == steps and all(k[jump] != k[jump - 1] for k in K)
    for name in ALL:
        res_n, tr = out["results"][name], out["traces"][name]
        s, cav = res_n["summary"], res_n["per_cavity"]
        assert 0.0 <= s["frac_locked"]["mean"] <= 1.0 and s["frac_locked"]["n"] == 2
        # the summary is the mean over cavities of the per-cavity values, which come from the trace
        for b in range(2):
            assert cav["mean_r"][b] == pytest.approx(sum(tr["r"][b]) / steps, abs=1e-4)
            assert cav["frac_locked"][b] == sum(x >= 0.1 for x in tr["r"][b]) / steps
        assert s["mean_r"]["mean"] == pytest.approx(sum(cav["mean_r"]) / 2)
        assert all(len(rec) == 1 for rec in cav["recovery_steps"])
        assert all(steps <= n <= 5 * steps for n in cav["round_trips"])  # 1 to 5 round trips per step
        assert len(tr["r"][0]) == steps and len(tr["angles_deg"][0]) == steps
        # K jumps: the steps after each cavity's first lock, sorted into bands of K
        bands = s["after_first_lock_by_K"]
        assert sum(b["steps"] for b in bands) == sum(steps - f + 1 for f in cav["first_lock_step"] if f is not None)
        assert all(round(b["K"][1] - b["K"][0], 9) == 0.1 and 0 <= b["locked"] <= 1 for b in bands)
    assert set(out["traces"]["hybrid"]["mode"][0]) <= {0, 1} and "mode" not in out["traces"]["esc"]
    assert all("r_read" not in out["traces"][n] for n in ALL)  # fields: the controllers read the paper's r itself
    # deep RL moves alpha1 in the checkpoint's 2 deg steps
    a = [x[0] for x in out["traces"]["rl"]["angles_deg"][0]]
    assert all(abs(abs(a[i + 1] - a[i]) - 2.0) < 1e-3 or abs(a[i + 1] - a[i]) < 1e-3 for i in range(steps - 1))
    assert (tmp_path / "control.png").stat().st_size > 0
    table = (tmp_path / "control.md").read_text()
    assert all(f"| {n} |" in table for n in ALL)
    locked_somewhere = all(out["results"][n]["summary"]["after_first_lock_by_K"] for n in ALL)
    assert ("per band of K" in table) == locked_somewhere


def test_a_measured_model_with_history_controls_imperfect_plates(tmp_path):
    """A model reading instruments with a stacked history runs in laserrl-control: the cavities
    start where the scenario says (through the history transform), every controller reads the
    instruments' reward, and with backlash the plates' true angles differ from the commands."""
    from laserrl.train import train

    model = tmp_path / "dqn"
    readings = ["env.observation=measured", "env.history=3", "env.instruments.spectrum_span=6",
                "env.instruments.spectrum_bins=16", "env.instruments.autocorrelation_points=16"]
    train(_compose(["experiment=smoke", *SMOKE_PHYSICS[:2], *readings, f"run_dir={model}", "train.progress=false",
                    "eval.plots=false"], name="config"))
    cfg = _compose(["controller=all", "scenario=drift_jumps", f"checkpoint={model}", "num_cavities=2", "scenario.steps=4",
                    "scenario.jumps.times=[2]", "compile=false", "plots=false", "progress=false", f"run_dir={tmp_path / 'run'}",
                    "plates.backlash_deg=1.0", "plates.noise_deg=0.2", "scenario.init_angles_deg.alpha1=60.0"])
    out = run_control(cfg)
    assert out["plates"] == {"noise_deg": 0.2, "backlash_deg": 1.0}
    starts = out["init_angles_deg"]
    for name in ALL:
        first = out["traces"][name]["angles_deg"][0][0][0]  # alpha1 after the first step, true angle
        assert starts[0][0] == 60.0 and abs(first - 60.0) < 15, (name, first)  # the scenario's start, not the training's
    assert all(0.0 <= out["results"][n]["summary"]["frac_locked"]["mean"] <= 1.0 for n in ALL)
    for name in ALL:  # what the controllers read: the instruments' reward, on its own scale, one per step
        read, r = np.array(out["traces"][name]["r_read"]), np.array(out["traces"][name]["r"])
        assert read.shape == r.shape == (2, 4) and np.isfinite(read).all() and not np.allclose(read, r)


def _always(checkpoint, out, K, sign, **stage):
    """A copy of ``checkpoint`` (siso) labelled as trained at ``K`` (and with the ``stage`` settings)
    whose greedy action always moves alpha1 by ``sign`` steps."""
    import copy

    import torch

    from laserrl.model import load_model, save_model

    state = load_model(checkpoint)
    meta = copy.deepcopy(state["meta"])
    meta["K"] = meta["config"]["stage"]["K"] = K
    meta["config"]["stage"].update(stage)
    weights = dict(state["qnet"])
    weights["head.4.weight"] = torch.zeros_like(weights["head.4.weight"])
    weights["head.4.bias"] = torch.tensor([10.0, 0.0, 0.0]) if sign < 0 else torch.tensor([0.0, 0.0, 10.0])
    save_model(out, weights, meta)
    return out


@pytest.mark.parametrize("rule", ["nearest", "trial"])
def test_a_bank_acts_with_the_member_its_rule_picks(checkpoint, tmp_path, rule):
    # two members that always step down (trained "at K = 0") and up (at K = 0.4); K jumps from 0.05 to >= 0.3
    down, up = _always(checkpoint, tmp_path / "down", 0.0, -1), _always(checkpoint, tmp_path / "up", 0.4, +1)
    bank = f"bank=[{down},{up}]" if rule == "nearest" else f"bank=[{up},{down}]"
    out = _run(["controller=rl", bank, f"bank_rule={rule}", "scenario.steps=6", "scenario.K0=0.05",
                "scenario.jumps.times=[3]", "scenario.jumps.range=[0.3,0.4]",
                "bank_trial.steps=2", "bank_trial.lock_r=10", "bank_trial.min_rise=10", "progress=false"], tmp_path)
    assert out["bank"] == ([str(down), str(up)] if rule == "nearest" else [str(up), str(down)])
    for b in range(2):
        a = [out["init_angles_deg"][b][0]] + [x[0] for x in out["traces"]["rl"]["angles_deg"][b]]
        moves = [round((a[t + 1] - a[t]) / 2.0) for t in range(6)]
        if rule == "nearest":  # told K: down before the jump, up after it
            assert moves == [-1 if k < 0.2 else 1 for k in out["K"][b]], (moves, out["K"][b])
        else:  # not told K: r never rises by 10, so each member gets 2 steps in turn, from the first
            assert moves == [1, 1, -1, -1, 1, 1], moves


def test_rl_steps_deg_sets_the_plate_turn_of_one_step_of_deep_RL(checkpoint, tmp_path):
    up = _always(checkpoint, tmp_path / "up", 0.0, +1)  # trained with 2 deg steps, always one step up
    for step in (None, 0.5):
        out = _run(["controller=rl", f"checkpoint={up}", "scenario.steps=3", "progress=false",
                    *([] if step is None else [f"rl_steps_deg={step}"])], tmp_path / str(step))
        assert out["rl_steps_deg"] == [2.0 if step is None else step]
        a = [out["init_angles_deg"][0][0]] + [x[0] for x in out["traces"]["rl"]["angles_deg"][0]]
        assert [a[t + 1] - a[t] for t in range(3)] == pytest.approx([out["rl_steps_deg"][0]] * 3)
    # rl_fine_from_r: the checkpoint's own 2 deg where the reward read is >= the level (r >= 0: every step)
    for level, step in ((0.0, 2.0), (1e9, 0.5)):
        out = _run(["controller=rl", f"checkpoint={up}", "scenario.steps=3", "progress=false", "rl_steps_deg=0.5",
                    f"rl_fine_from_r={level}"], tmp_path / f"fine{level}")
        assert out["rl_fine"] == {"steps_deg": [2.0], "from_r": level}
        a = [out["init_angles_deg"][0][0]] + [x[0] for x in out["traces"]["rl"]["angles_deg"][0]]
        assert [a[t + 1] - a[t] for t in range(3)] == pytest.approx([step] * 3)


def test_deep_RL_turns_as_a_checkpoint_trained_with_fine_steps_near_a_lock(checkpoint, tmp_path):
    # trained in 2 deg steps with 0.25 deg from fine_from on: its own rule unless the settings replace it
    for level, step in ((0.0, 0.25), (1e9, 2.0)):
        up = _always(checkpoint, tmp_path / f"up{level}", 0.0, +1, fine_steps_deg=[0.25], fine_from=level)
        for i, (settings, expected) in enumerate((([], step), ([f"rl_fine_from_r={1e9 - level}"], 2.0 if level == 0 else 0.25),
                                                  (["rl_steps_deg=1.0"], 0.25 if level == 0 else 1.0))):
            out = _run(["controller=rl", f"checkpoint={up}", "scenario.steps=3", "progress=false", *settings],
                       tmp_path / f"{level}-{i}")
            assert out["rl_fine"]["steps_deg"] == [0.25]
            a = [out["init_angles_deg"][0][0]] + [x[0] for x in out["traces"]["rl"]["angles_deg"][0]]
            assert [a[t + 1] - a[t] for t in range(3)] == pytest.approx([expected] * 3), (level, settings)


def test_a_bank_refuses_a_checkpoint_beside_it_and_unknown_rules(checkpoint, tmp_path):
    with pytest.raises(ConfigError, match="not both"):
        _run(["controller=rl", f"checkpoint={checkpoint}", f"bank=[{checkpoint}]"], tmp_path)
    with pytest.raises(ConfigError, match="bank_rule"):
        _run(["controller=rl", f"bank=[{checkpoint}]", "bank_rule=max_q"], tmp_path)
    assert not (tmp_path / "control.json").exists()


def test_all_runs_only_the_controllers_named(tmp_path):
    out = _run(["controller=all", "controller.only=[ga,esc]", "metric_controller=esc"], tmp_path)
    assert out["controllers"] == ["ga", "esc"] and set(out["results"]) == {"ga", "esc"}
    table = (tmp_path / "control.md").read_text()
    assert "| esc |" in table and "| ga |" in table and "| hill_climb |" not in table


def test_sweep_metric(tmp_path):
    cfg = _compose(["controller=esc", "scenario=constant", *SMOKE_PHYSICS, "num_cavities=2", "scenario.steps=3", "plots=false",
                    f"run_dir={tmp_path}", "metric=mean_r"])
    out = run_control(cfg)
    assert sweep_metric(out, cfg) == pytest.approx(out["results"]["esc"]["summary"]["mean_r"]["mean"])


def test_hostile_value_on_the_command_line_is_one_line(tmp_path):
    exe = Path(sys.executable).parent / "laserrl-control"
    res = subprocess.run([str(exe), "controller=esc", "controller.max_step_deg=0", f"hydra.run.dir={tmp_path}"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines() == ["laserrl-control: error: controller: max_step_deg must be > 0, got 0"]
    assert not (tmp_path / "control.json").exists()


def test_the_fixed_K_grid_runs_the_K_blind_agent_as_laserrl_eval_scores_it(tmp_path):
    """experiment=any_k_grid_hybrid: 10 cavities at each of laserrl-eval's 19 K values; a cavity
    succeeds as in laserrl-eval (held_to_end), and control.md gives the success per K."""

    from laserrl.control.metrics import held_to_end

    cfg = _compose(["experiment=any_k_grid_hybrid"])
    assert cfg.num_cavities == 10 * len(cfg.scenario.K0) == 190 and cfg.checkpoint == "zoo:miso-any-k-gru-s3"
    out = run_control(_compose(["experiment=any_k_grid_hybrid", "num_cavities=4", "scenario.K0=[0.0,0.3]",
                                "scenario.steps=3", "compile=false", "plots=false", "progress=false",
                                f"run_dir={tmp_path}"]))
    assert out["controllers"] == ["hybrid", "rl"]
    assert np.array_equal(np.array(out["K"])[:, 0], [0.0, 0.3, 0.0, 0.3])
    for name in out["controllers"]:
        r = np.array(out["traces"][name]["r"])
        held = held_to_end(r, 0.15, 0.1)
        summary = out["results"][name]["summary"]
        assert summary["held_to_end_by_K0"] == {"0": held[[0, 2]].mean(), "0.3": held[[1, 3]].mean()}
    table = (tmp_path / "control.md").read_text()
    assert "per K0" in table and "| hybrid | " in table.split("per K0")[1]


@pytest.mark.parametrize("name, base", [("any_k_hybrid", "measured_hybrid"), ("any_k_grid_hybrid_coarse", "any_k_grid_hybrid")])
def test_the_coarse_search_hybrids_change_only_the_model_and_the_hybrids_settings(name, base):
    """experiment=any_k_hybrid and any_k_grid_hybrid_coarse (docs/measured.md): their base experiment with
    zoo:miso-any-k-gru-wide, deep RL in 1 deg steps (its own 0.5 deg at the instruments' lock level), settle_steps=3,
    lock_steps=5 and lock_r=0.30, and nothing else changed
    (the drift run also runs the agent alone beside the hybrid, compiled)."""
    settings = ["checkpoint=zoo:miso-any-k-gru-wide", "rl_steps_deg=1.0", "rl_fine_from_r=0.454",
                "controller.hybrid.settle_steps=3", "controller.hybrid.lock_steps=5", "controller.hybrid.lock_r=0.30"]
    if name == "any_k_hybrid":
        settings += ["controller.only=[hybrid,rl]", "compile=true"]
    got = OmegaConf.to_container(_compose([f"experiment={name}", "run_dir=x"]), resolve=True)
    want = OmegaConf.to_container(_compose([f"experiment={base}", "run_dir=x", *settings]), resolve=True)
    assert got == want
    assert want != OmegaConf.to_container(_compose([f"experiment={base}", "run_dir=x"]), resolve=True)
