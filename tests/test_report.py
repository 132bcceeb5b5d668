"""laserrl-report end to end with tiny budgets and grids, its table, and its input errors."""
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from laserrl.checkpoint import CheckpointError
from laserrl.config import ConfigError
from laserrl.report.app import run_report
from laserrl.report.claims import REQUIRED
from laserrl.report.context import grid, widen
from laserrl.report.figures import FIGURES
from laserrl.report.spot import as_overrides
from laserrl.paths import CONF_DIR

CONF = Path(CONF_DIR)

# every model trained on the spot in seconds: tiny physics, few frames, 3-step protocols
TINY = [
    "threads=1", "report.checkpoints.siso=null", "report.checkpoints.duo=null", "report.checkpoints.miso=null",
    "report.checkpoints.k_base=null", "report.checkpoints.bank=[]", "report.train_bank=true",
    "+report.train.common.env={num_envs:8,max_round_trips:5,compile:false,physics:{n:64,z_steps:2}}",
    "+report.train.common.collector.frames_per_batch=32", "+report.train.common.replay.init_random_frames=32",
    "+report.train.common.optim.batch_size=16",
    "+report.train.common.stage={max_steps:3,protocol:{steps:3,starts_deg:[-30,-20],repeats:2}}",
    "+report.train.common.eval={steps:3,after_training:false}",
    "report.train.siso.train.total_frames=64", "report.train.siso.train.eval_every_frames=32",
    "report.train.duo.train.total_frames=64", "report.train.miso.train.total_frames=64",
    "report.train.k_base.train.total_frames=64",
    "report.train.bank.transfer.Ks=[0.0,0.2]", "report.train.bank.transfer.finetune.train.total_frames=64",
    "report.fig3_starts=[-30]", "report.landscape.alpha1_deg=[-30,-20,5]",
    "report.landscape.map_alpha1_deg=[-30,-20,5]", "report.landscape.map_alpha2_deg=[-5,0,5]",
    "report.landscape.settle_round_trips=10", "report.generalisation.K=[0.0,0.2]", "report.generalisation.steps=3",
    "report.checkpoints.any_k=zoo:miso-any-k",  # beyond the paper: the shipped K-blind agent, 3 steps per K
    "report.control=['experiment=miso_hybrid','num_cavities=2','scenario.steps=6','scenario.jumps.times=[2,4]']",
]


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """One real ``laserrl-report`` run that trains every model on the spot."""
    tmp = tmp_path_factory.mktemp("report")
    exe = Path(sys.executable).parent / "laserrl-report"
    res = subprocess.run([str(exe), *TINY, f"report.out_dir={tmp / 'docs'}", f"hydra.run.dir={tmp / 'run'}"],
                         cwd=tmp, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    return tmp, res


def test_report_writes_every_figure(smoke):
    tmp, res = smoke
    for name in FIGURES:
        path = tmp / "docs" / "figures" / f"{name}.png"
        assert path.exists() and 0 < path.stat().st_size < 300_000, name
    doc = (tmp / "docs" / "reproduction.md").read_text()
    assert "Not drawn" not in doc
    assert doc.count("](figures/") == len(FIGURES)


def test_table_has_every_required_claim_with_numbers(smoke):
    tmp, _ = smoke
    report = json.loads((tmp / "run" / "report.json").read_text())
    doc = (tmp / "docs" / "reproduction.md").read_text()
    claims = {c["key"]: c for c in report["claims"]}
    assert set(REQUIRED) <= set(claims)
    table = [line for line in doc.splitlines() if line.startswith("| ")]
    for key in REQUIRED:
        c = claims[key]
        row = next(line for line in table if line.startswith(f"| {c['claim'].replace('|', chr(92) + '|')} |"))
        cells = [x.strip() for x in re.split(r"(?<!\\)\|", row)[1:-1]]
        assert cells[1], (key, cells)  # the paper's number, or "not stated" (no number for the width)
        assert re.search(r"\d", cells[2]), (key, cells)  # laserrl's number
        assert re.fullmatch(r"(\[[A-Z]\] ?)+", cells[3]), (key, cells)  # the commands behind it
    # the commands are listed: this report's and the training runs it made
    assert doc.count("`laserrl-train ") >= 4 and "`laserrl-report " in doc


def test_report_numbers_match_what_it_measured(smoke):
    tmp, _ = smoke
    report = json.loads((tmp / "run" / "report.json").read_text())
    numbers, claims = report["numbers"], {c["key"]: c for c in report["claims"]}
    # replays of the greedy rollouts reproduce them (the fields drawn are the agent's)
    assert max(numbers["replay_max_abs_dr"].values()) < 1e-3
    r_settled = numbers["paths"]["r_settled"]
    assert f"r = {r_settled[0]:.4f}" in claims["r_modelocked"]["laserrl"]
    assert f"r = {r_settled[1]:.4f}" in claims["r_planewave"]["laserrl"]
    # the straight path has as many steps as the agent's and ends where the agent ended
    assert len(numbers["paths"]["r_straight"]) == numbers["paths"]["steps"] == len(numbers["paths"]["agent_path_deg"])
    assert report["meta"]["trained_on_the_spot"].keys() == {"siso", "duo", "miso", "k_base", "bank"}
    # the claims about other K start from the four-controller model at K = 0.1 (k_base): the bank is fine-tuned
    # from it, it is the one model of fig. 6 and it drives the hybrid of fig. 7
    from laserrl.model import load_model

    k_base = report["checkpoints"]["k_base"]
    assert load_model(k_base)["config"]["stage"]["K"] == 0.1
    assert len(load_model(k_base)["config"]["stage"]["controlled"]) == 4
    assert all(load_model(m)["config"]["init_from"] == k_base for m in report["checkpoints"]["bank"])
    assert numbers["control"]["scenario"] == "drift_jumps_wide"
    # fig. 7: every controller ran on the same cavities; the claim quotes the hybrid's measured numbers
    control = numbers["control"]
    assert {"hybrid", "rl", "esc", "random_search", "hill_climb", "ga"} <= set(control) and control["num_cavities"] == 2
    assert f"hybrid: locked {control['hybrid']['frac_locked']:.2f}" in claims["hybrid"]["laserrl"]
    # the K-blind agent ran on fig. 6's K values and draws and is compared with the rules measured there
    any_k = json.loads((tmp / "run" / "any_k" / "eval.json").read_text())
    assert any_k["K"] == [0.0, 0.2] and any_k["steps"] == 3
    ok = sum(v["success_rate"] >= 0.9 for v in any_k["by_K"].values())
    assert f"({ok} / 2 values" in claims["any_k"]["laserrl"] and "the bank told K" in claims["any_k"]["laserrl"]
    assert "the last 4 readings stacked" in claims["any_k"]["note"]  # the memory of zoo:miso-any-k


def _compose(tmp_path, *overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="report", overrides=[f"run_dir={tmp_path / 'run'}",
                                                         f"report.out_dir={tmp_path / 'docs'}", *overrides])


def test_bad_input_names_the_input_and_keeps_the_old_report(smoke, tmp_path):
    siso = smoke[0] / "run" / "train" / "siso"
    (tmp_path / "docs").mkdir()
    old = tmp_path / "docs" / "reproduction.md"
    old.write_text("earlier report")
    cases = [
        ((f"report.checkpoints.duo={siso}",), ConfigError, r"report.checkpoints.duo: .* controls \['alpha1'\]"),
        ((f"report.checkpoints.miso={tmp_path}/nope",), CheckpointError, "model not found"),
        (("report.checkpoints.miso=zoo:nope",), CheckpointError, "zoo:nope: no such model in the zoo"),
        ((f"report.results.transfer=[{tmp_path}/transfer.json]",), ConfigError, "report.results.transfer: no such file"),
        (("report.figures=[fig9]",), ConfigError, r"report.figures: unknown figure\(s\) \['fig9'\]"),
        (("report.landscape.alpha1_deg=[0,-10,2]",), ConfigError, r"report.landscape.alpha1_deg must have first < last"),
    ]
    for overrides, error, message in cases:  # all fail before any training or simulation
        with pytest.raises(error, match=message):
            run_report(_compose(tmp_path, f"report.checkpoints.siso={siso}", *overrides))
    assert old.read_text() == "earlier report"


def test_grids_and_overrides():
    assert grid([-4, 4, 2], "g").tolist() == [-4.0, -2.0, 0.0, 2.0, 4.0]
    with pytest.raises(ConfigError, match="multiple of step"):
        grid([0, 5, 2], "g")
    # widened by whole steps until it holds both ends of a path
    assert widen(torch.tensor([0.0, 2.0, 4.0]), -3.0, 4.5).tolist() == [-4.0, -2.0, 0.0, 2.0, 4.0, 6.0]
    assert as_overrides({"stage": "duo", "train": {"total_frames": 64}}, {"train": {"total_frames": 8}, "x": None}) == \
        ["stage=duo", "train.total_frames=8", "x=null"]


def test_a_bank_model_fine_tuned_again_over_a_K_range_counts_every_fine_tuning(tmp_path):
    import shutil

    from laserrl.model import load_model, model_metadata, save_model
    from laserrl.report.claims import _K_text, _finetune_episodes

    def save(name, frames, max_steps, K, init_from, controlled=("alpha1",)):
        config = {"env": {}, "agent": {}, "init_from": init_from,
                  "stage": {"K": K, "max_steps": max_steps, "controlled": list(controlled),
                             "steps_deg": [2.0] * len(controlled)}}
        return str(save_model(tmp_path / name, {"w": torch.zeros(1)}, model_metadata(config, 3 ** len(controlled),
                                                                                       frames=frames)))

    base = save("base", 40960, 20, 0.1, None)  # trained from scratch: not counted
    point = save("point", 6400, 40, 0.4, base)  # 160 episodes
    ranged = save("ranged", 1280, 40, [0.3, 0.4], point)  # 32 more
    assert _finetune_episodes(load_model(ranged)) == 192
    assert _finetune_episodes(load_model(point)) == 160
    # a base grown by the curriculum (two controllers, then four) is not a fine-tuning
    four = ("alpha1", "alpha2", "alpha3", "alpha_p")
    duo = save("duo", 20480, 40, 0.1, None, ("alpha1", "alpha2"))
    miso = save("miso", 81920, 100, 0.1, duo, four)
    tuned = save("tuned", 2000, 100, -0.2, miso, four)
    assert _finetune_episodes(load_model(tuned)) == 20
    shutil.rmtree(point)  # a parent that is gone ends the chain
    assert _finetune_episodes(load_model(ranged)) == 32
    assert _K_text([0.3, 0.4]) == "[0.3, 0.4]" and _K_text(-0.2) == "-0.2"


def test_without_a_bank_the_rows_about_other_K_say_they_are_not_backed_by_the_zoo():
    from types import SimpleNamespace

    from laserrl.report.claims import _K_bank, _K_single, _episodes_finetune
    from laserrl.report.context import NOT_IN_ZOO
    from laserrl.report.figures import FigureSkipped, fig6_generalisation

    ctx = SimpleNamespace(bank=[], cfg={"results": {"generalisation": None, "transfer": []}}, has_generalisation=False)
    for row in (_K_single(ctx), _K_bank(ctx), _episodes_finetune(ctx)):
        assert row.laserrl == NOT_IN_ZOO and row.paper
    with pytest.raises(FigureSkipped, match="not backed by the zoo"):
        fig6_generalisation(ctx, Path("unused.png"))


def test_one_model_over_K_backs_the_one_model_row_and_not_the_banks():
    from types import SimpleNamespace

    from laserrl.results import as_generalisation
    from laserrl.report.claims import _K_bank, _K_single
    from laserrl.report.context import NOT_IN_ZOO

    by_K = {"-0.2": {"success_rate": 0.5, "mean_final_reward": 0.1}, "0.1": {"success_rate": 1.0, "mean_final_reward": 0.2}}
    one = {"success_rate": 0.75, "mean_final_reward": 0.15, "mean_steps_to_lock": 9.0, "by_K": by_K, "stage": "miso"}
    g = as_generalisation(one, "zoo:m")
    assert g["K"] == [-0.2, 0.1] and g["rules"]["single"]["by_K"] == by_K and g["grid_success"] == {"single": 0.5}
    assert as_generalisation(g) == g  # a bank evaluation passes as it is
    with pytest.raises(ConfigError, match="not an evaluation over K"):
        as_generalisation({"success_rate": 1.0})
    ctx = SimpleNamespace(bank=[], cfg={"results": {"generalisation": "G/eval.json"}, "generalisation": {"steps": None}},
                          has_generalisation=True, generalisation=g, commands={}, models={},
                          command_for=lambda path: f"laserrl-eval ... ({path})")
    assert "K in" in _K_single(ctx).laserrl and "1 / 2 grid points" in _K_single(ctx).laserrl
    assert _K_bank(ctx).laserrl == NOT_IN_ZOO


def test_bank_entries_keep_ensembles_and_bank_paths_flattens_them():
    from laserrl.report.context import bank_entries, bank_paths

    bank = bank_entries([Path("a.pt"), ["b0.pt", Path("b1.pt")], "c.pt"])
    assert bank == ["a.pt", ["b0.pt", "b1.pt"], "c.pt"]
    assert bank_paths(bank) == ["a.pt", "b0.pt", "b1.pt", "c.pt"]
    assert bank_entries(None) == [] == bank_paths([])


def _generalisation(single, nearest, max_q):
    """A generalisation result at K = -0.2 and 0.1 with these success rates per rule."""
    def rule(rates):
        return {"by_K": {K: {"success_rate": s, "mean_final_reward": 0.1 + s / 10, "locked_end_deg": [50.0, 70.0] if s else None,
                             "starts_deg": [-40.0, -10.0]} for K, s in zip(("-0.2", "0.1"), rates)}}
    return {"K": [-0.2, 0.1], "rules": {"single": rule(single), "nearest": rule(nearest), "max_q": rule(max_q)}}


def test_report_notes_come_from_the_measured_rules():
    from laserrl.report.claims import _far_locks, _max_q_note

    g = _generalisation(single=(0.0, 1.0), nearest=(1.0, 1.0), max_q=(0.0, 1.0))
    assert _far_locks(g) == ("Where the one model fails and the nearest bank model locks, that model ends at alpha1 in "
                             "K = -0.2: [50, 70] deg (starts in [-40, -10] deg).")
    assert _max_q_note(g).startswith("Highest-Q succeeds at fewer K (1 / 2) than nearest-K (2)")
    g = _generalisation(single=(1.0, 1.0), nearest=(1.0, 1.0), max_q=(1.0, 1.0))
    assert _far_locks(g) == ""  # nothing to explain where the one model succeeds
    assert _max_q_note(g) == "Highest-Q succeeds at as many K as nearest-K (2 / 2)."
