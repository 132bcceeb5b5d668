"""The real console scripts with tiny overrides: they run, write what they promise, and
turn bad input into one clear line without a traceback."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

SMOKE = ["experiment=smoke", "env.physics.n=64", "env.physics.z_steps=2"]


def run(cmd, *args, cwd):
    exe = Path(sys.executable).parent / cmd
    return subprocess.run([str(exe), *args], cwd=cwd, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("train")
    res = run("laserrl-train", *SMOKE, f"hydra.run.dir={out}", cwd=out)
    assert res.returncode == 0, res.stderr[-2000:]
    return out, res


def test_train_writes_checkpoint_eval_and_prints_path(trained):
    out, res = trained
    ckpt = out / "checkpoints" / "last.pt"
    assert f"checkpoint: {ckpt}" in res.stdout
    state = torch.load(ckpt, weights_only=False)
    for key in ("qnet", "target", "optimizer", "epsilon", "frames", "updates", "config"):
        assert key in state
    assert state["frames"] >= 64 and state["config"]["stage"]["name"] == "siso"
    # the shareable model next to it: the same weights, its evaluation and card in model.json
    from laserrl.model import load_model

    model = load_model(out)
    assert model["dir"] == str(out / "model") and all(torch.equal(model["qnet"][k], v) for k, v in state["qnet"].items())
    assert model["meta"]["eval"]["success_rate"] == json.loads((out / "eval.json").read_text())["success_rate"]
    card = model["meta"]["card"]
    assert card["command"].startswith("laserrl-train experiment=smoke") and card["frames"] == state["frames"]
    result = json.loads((out / "eval.json").read_text())
    assert len(result["per_start"]) == 2 and 0.0 <= result["success_rate"] <= 1.0
    assert all(len(p["angle_path_deg"]) == 3 for p in result["per_start"])


def test_collector_does_not_ask_for_recurrent_policy_transforms(trained):
    # the Q-network is feed-forward; torchrl 0.14 warns (and 0.15 would append an
    # InitTracker to the env) unless the collector is told to leave the env alone
    _, res = trained
    assert "missing transforms required by the policy" not in res.stderr


def test_eval_entry_point_on_a_checkpoint_at_another_K_and_cavity(trained, tmp_path):
    out, _ = trained
    res = run("laserrl-eval", f"checkpoint={out}", "eval.K=0.2", "eval.steps=2", "eval.starts_deg=[-30]",
              "env.physics.g0=1.8", "eval.compile=false", "eval.plots=false", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    result = json.loads((tmp_path / "eval.json").read_text())
    assert result["K"] == [0.2] and result["per_start"][0]["K"] == 0.2
    assert result["physics_changed"] == {"g0": 1.8}
    assert f"eval: {tmp_path / 'eval.json'}" in res.stdout


def _one_line_error(res, *words):
    assert res.returncode != 0
    assert "Traceback" not in res.stderr
    lines = [line for line in res.stderr.splitlines() if "error" in line.lower()]
    assert lines, res.stderr
    for w in words:
        assert w in res.stderr


def test_missing_checkpoint(tmp_path):
    res = run("laserrl-eval", f"checkpoint={tmp_path}/nope", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    _one_line_error(res, "model not found")


def test_incompatible_head(trained, tmp_path):
    out, _ = trained
    res = run("laserrl-eval", f"checkpoint={out}", "stage=duo", "eval.compile=false", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    _one_line_error(res, "3-action head", "9 actions")


def test_truncated_model(trained, tmp_path):
    import shutil

    out, _ = trained
    bad = tmp_path / "bad"
    shutil.copytree(out / "model", bad)
    (bad / "model.safetensors").write_bytes((out / "model" / "model.safetensors").read_bytes()[:500])
    res = run("laserrl-eval", f"checkpoint={bad}", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    _one_line_error(res, "unreadable")


def test_unknown_key_and_wrong_type(tmp_path):
    res = run("laserrl-train", "optim.nosuchkey=1", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    _one_line_error(res, "nosuchkey")
    res = run("laserrl-train", *SMOKE, "optim.lr=fast", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    _one_line_error(res, "optim.lr")
    res = run("laserrl-train", *SMOKE, "env.num_envs=0", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    _one_line_error(res, "env.num_envs")
    assert not (tmp_path / "checkpoints").exists()


@pytest.mark.parametrize("extra", [["collector=multi_sync", "collector.num_workers=2", "collector.frames_per_batch=16", "env.num_envs=8",
                                    "agent.n_steps=2"],
                                   ["logger.backend=csv"], ["logger.backend=tensorboard"],
                                   ["logger.backend=wandb", "replay=uniform", "agent.target.kind=hard", "agent.exploration.kind=linear"]])
def test_train_variants_run_and_log(tmp_path, extra):
    res = run("laserrl-train", *SMOKE, *extra, f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert (tmp_path / "checkpoints" / "last.pt").exists()
    if "logger.backend=csv" in extra:
        scalars = tmp_path / "logs"
        names = {p.relative_to(next(scalars.iterdir()) / "scalars").as_posix() for p in scalars.rglob("*.csv")}
        assert {"train/r_mean.csv", "train/epsilon.csv", "eval/mean_final_reward.csv"} <= names
    if "agent.n_steps=2" in extra:  # n-step transitions (with their step counts) reached the replay buffer
        assert list((tmp_path / "checkpoints").rglob("steps_to_next_obs.memmap"))
    if "logger.backend=tensorboard" in extra:
        assert list((tmp_path / "logs").rglob("events.out.tfevents*"))
    if "logger.backend=wandb" in extra:
        assert list(tmp_path.rglob("offline-run-*"))


def test_warm_start_same_stage_grown_stage_and_refusal(trained, tmp_path):
    out, _ = trained
    res = run("laserrl-train", *SMOKE, f"init_from={out}", f"hydra.run.dir={tmp_path / 'ok'}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    # siso -> duo: the head grows from 3 to 9 actions by the documented rule
    res = run("laserrl-train", *SMOKE, f"init_from={out}", "stage=duo", "stage.max_steps=3", "eval.steps=2",
              f"hydra.run.dir={tmp_path / 'duo'}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert torch.load(tmp_path / "duo" / "checkpoints" / "last.pt", weights_only=False)["num_actions"] == 9
    # alpha1 actions cannot become alpha2 actions
    res = run("laserrl-train", *SMOKE, f"init_from={out}", "stage.controlled=[alpha2]",
              f"hydra.run.dir={tmp_path / 'bad'}", cwd=tmp_path)
    _one_line_error(res, "3-action head", "['alpha2']")
    assert not (tmp_path / "bad" / "checkpoints").exists()


def test_warm_started_keep_best_run_validates_its_starting_weights_and_reselects(trained, tmp_path):
    # fine-tuning with train.keep_best: the warm start is a candidate, so the run cannot end worse than it began;
    # train.reselect: the 2 best of its 3 validations are validated again on other draws, the winner there kept
    out, _ = trained
    res = run("laserrl-train", *SMOKE, f"init_from={out}", "train.keep_best=true", "train.eval_every_frames=32",
              "train.reselect={top:2,repeats:2,K:[0.0,0.2]}", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    validated = [h for h in json.loads((tmp_path / "history.json").read_text()) if "eval/success_rate" in h]
    assert [h["frames"] for h in validated] == [0, 32, 64]
    summary = json.loads((tmp_path / "summary.json").read_text())
    best = summary["best"]
    assert summary["frames_to_success"] is None
    finalists = best["reselect"]["finalists"]
    assert len(finalists) == 2 and len({f["frames"] for f in finalists}) == 2
    top_two = sorted((h["eval/success_rate"] for h in validated), reverse=True)[:2]
    assert [f["validation"][0] for f in finalists] == top_two  # best-validated first
    chosen = max(finalists, key=lambda f: (f["success_rate"], f["mean_final_reward"]))
    assert best["frames"] == chosen["frames"] and best["reselect"]["success_rate"] == chosen["success_rate"]
    # the model holds the chosen weights; the checkpoint keeps the finalists for a resumed run
    from laserrl.model import load_model
    from laserrl.resume import load_run

    saved = {f["frames"]: f["weights"] for f in load_run(tmp_path)["finalists"]}
    assert set(saved) == {f["frames"] for f in finalists}
    qnet = load_model(tmp_path)["qnet"]
    assert all(torch.equal(qnet[k], v) for k, v in saved[chosen["frames"]].items())


def test_curriculum_runs_stages_in_order_with_warm_starts(tmp_path):
    # experiment=smoke keeps it tiny; the curriculum keys are those of experiment=curriculum
    res = run("laserrl-train", *SMOKE, "+curriculum.stages=[siso,duo]",
              "+curriculum.total_frames=[32,32]", "+curriculum.max_minutes=[null,null]",
              "+curriculum.stage_overrides.duo.max_steps=3", "eval.starts_deg=null", "eval.steps=null",
              "+curriculum.stage_overrides.duo.protocol.steps=2", "+curriculum.stage_overrides.siso.protocol.steps=2",
              f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    first = torch.load(tmp_path / "01-siso" / "checkpoints" / "last.pt", weights_only=False)
    second = torch.load(tmp_path / "02-duo" / "checkpoints" / "last.pt", weights_only=False)
    assert (first["num_actions"], second["num_actions"]) == (3, 9)
    assert second["config"]["init_from"] == str(tmp_path / "01-siso" / "model")
    assert res.stdout.index("stage 1/2: siso") < res.stdout.index("stage 2/2: duo")
    # each stage is evaluated with its own protocol: siso from 16 alpha1 starts, duo from 5, with hold_r
    ev1 = json.loads((tmp_path / "01-siso" / "eval.json").read_text())
    ev2 = json.loads((tmp_path / "02-duo" / "eval.json").read_text())
    assert (len(ev1["per_start"]), ev1["hold_r"], ev1["steps"]) == (16, None, 2)
    assert (len(ev2["per_start"]), ev2["hold_r"], ev2["steps"]) == (5, 0.1, 2)


def test_any_k_experiment_trains_one_measured_agent_over_the_K_range(tmp_path):
    """experiment=miso_any_k (its four-controller stage, tiny): K drawn from [-0.2, 0.4] and moving in
    training, validation and evaluation at seven fixed K, measured readings with a history of 4."""
    tiny = ["threads=1", "env.num_envs=8", "env.max_round_trips=3", "env.compile=false", "env.physics.n=64",
            "env.physics.z_steps=2", "env.instruments.spectrum_span=6", "env.instruments.spectrum_bins=16",
            "env.instruments.autocorrelation_points=16", "collector.frames_per_batch=32", "replay.init_random_frames=32",
            "optim.batch_size=16", "logger=none", "train.plots=false", "train.progress=false"]
    res = run("laserrl-train", "experiment=miso_any_k", *tiny, "curriculum.stages=[miso]", "curriculum.total_frames=[64]",
              "curriculum.max_minutes=[null]", "+curriculum.stage_overrides.miso.protocol.steps=3",
              "+curriculum.stage_overrides.miso.max_steps=4", "curriculum.config_overrides.miso.train.eval_every_frames=32",
              f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    ev = json.loads((tmp_path / "01-miso" / "eval.json").read_text())
    assert ev["K"] == [-0.2, -0.1, 0.0, 0.1, 0.2, 0.3, 0.4] and len(ev["per_start"]) == 7 * 3
    meta = json.loads((tmp_path / "01-miso" / "model" / "model.json").read_text())
    assert (meta["observation"], meta["memory"]) == ("measured", {"history": 4})
    assert meta["config"]["stage"]["K"] == [-0.2, 0.4] and meta["config"]["stage"]["K_drift"] > 0
    assert meta["config"]["env"]["physics_spread"] == 0.1  # trained on cavities within +-10 % of the nominal one


def test_any_k_experiment_with_a_gru_records_its_memory_and_evaluates(tmp_path):
    """experiment=miso_any_k_gru (its four-controller stage, tiny): sequences of 4 steps in replay, the
    GRU recorded in the model card, and laserrl-eval and laserrl-control run the model as it was saved."""
    tiny = ["threads=1", "env.num_envs=8", "env.max_round_trips=3", "env.compile=false", "env.physics.n=64",
            "env.physics.z_steps=2", "env.instruments.spectrum_span=6", "env.instruments.spectrum_bins=16",
            "env.instruments.autocorrelation_points=16", "env.gru_size=8", "collector.frames_per_batch=32",
            "replay.init_random_frames=32", "optim.batch_size=16", "logger=none", "train.plots=false",
            "train.progress=false"]
    res = run("laserrl-train", "experiment=miso_any_k_gru", *tiny, "curriculum.stages=[miso]", "curriculum.total_frames=[64]",
              "curriculum.max_minutes=[null]", "+curriculum.stage_overrides.miso.protocol.steps=3",
              "+curriculum.stage_overrides.miso.max_steps=4", "curriculum.config_overrides.miso.train.eval_every_frames=32",
              "curriculum.config_overrides.miso.eval.K=[0.1]", "++curriculum.config_overrides.miso.eval.held_steps=2",
              f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert json.loads((tmp_path / "01-miso" / "eval.json").read_text())["held_steps"] == 2  # validated by it too
    model = tmp_path / "01-miso" / "model"
    meta = json.loads((model / "model.json").read_text())
    assert (meta["observation"], meta["memory"]) == ("measured", {"history": 1, "gru_size": 8})
    res = run("laserrl-eval", f"checkpoint={model}", "eval.steps=3", "eval.K=[0.0,0.3]", "eval.repeats=2",
              "eval.held_steps=2", "eval.plots=false", "eval.compile=false", f"hydra.run.dir={tmp_path / 'eval'}",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    result = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert len(result["per_start"]) == 4 and result["held_steps"] == 2
    # a success locked by the second of the three steps (held for the last two)
    assert all(p["steps_to_lock"] <= 2 for p in result["per_start"] if p["success"])
    failures = result["failures"]  # how the failed draws failed, counted and printed
    assert failures["failed"] == sum(not p["success"] for p in result["per_start"])
    assert f"never locked {failures['never_locked']}" in res.stdout
    gap = result["hold_value_gap"]  # the GRU's Q-values: how it values holding still (the first step is never from a lock)
    assert set(gap) == {"from_lock", "searching"} and gap["searching"] >= 0
    res = run("laserrl-control", "controller=all", "scenario=constant", f"checkpoint={model}", "num_cavities=2",
              "scenario.steps=3", "compile=false", "plots=false", "progress=false", f"hydra.run.dir={tmp_path / 'control'}",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert set(json.loads((tmp_path / "control" / "control.json").read_text())["controllers"]) >= {"rl", "hybrid"}


def test_transfer_then_bank_generalisation(trained, tmp_path):
    """experiment=transfer_k fine-tunes the base to another K (and trains from scratch, here
    through a curriculum whose earlier stage is the base: transfer.scratch_from, whose frames
    count), counting frames to success; laserrl-eval then evaluates base + fine-tuned as a bank."""
    base, _ = trained
    base_frames = json.loads((base / "summary.json").read_text())["frames"]
    res = run("laserrl-train", "experiment=[smoke,transfer_k]", *SMOKE[1:], f"transfer.base={base}",
              f"transfer.scratch_from={base}",
              "transfer.Ks=[0.0]", "transfer.finetune.train.total_frames=64", "transfer.scratch.train.total_frames=64",
              "train.eval_every_frames=32", "train.stop_at_success=0.0", "eval.steps=2", "eval.starts_deg=[-30]",
              "+transfer.by_K={0:{stage:{max_steps:3}},0.3:{stage:{max_steps:5}}}",
              f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    # per-K settings reach both runs at that K, and only that K's
    for label in ("finetune", "scratch"):
        sub = torch.load(tmp_path / f"K+0.00-{label}" / "checkpoints" / "last.pt", weights_only=False)["config"]
        assert sub["stage"]["max_steps"] == 3
    out = json.loads((tmp_path / "transfer.json").read_text())
    (row,) = out["rows"]
    # a success-rate target of 0 is met by the evaluation before training: no frames needed, but the
    # scratch run's curriculum needed the base's frames first
    assert row["K"] == 0.0 and row["finetune"]["frames_to_success"] == 0 and row["finetune"]["frames"] == 0
    assert row["scratch"]["frames_to_success"] == base_frames == row["scratch"]["frames"] == out["scratch_frames_before"]
    assert row["finetune"]["frames_before"] == 0 and "earlier stages" in (tmp_path / "transfer.md").read_text()
    from laserrl.model import load_model

    scratch = load_model(tmp_path / "K+0.00-scratch")
    assert scratch["config"]["init_from"] == str(base) and scratch["meta"]["card"]["frames_since_scratch"] == base_frames
    tuned = tmp_path / "K+0.00-finetune" / "model"
    state = torch.load(tmp_path / "K+0.00-finetune" / "checkpoints" / "last.pt", weights_only=False)
    assert state["config"]["stage"]["K"] == 0.0 and state["config"]["init_from"] == str(base)
    table = (tmp_path / "transfer.md").read_text()
    assert "| 0 |" in table
    # run again in the same directory: finished sub-runs are reused, not retrained
    res = run("laserrl-train", "experiment=[smoke,transfer_k]", *SMOKE[1:], f"transfer.base={base}",
              f"transfer.scratch_from={base}", "transfer.Ks=[0.0]", "train.eval_every_frames=32", "train.stop_at_success=0.0",
              f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("reusing") == 2 and (tmp_path / "transfer.md").read_text() == table

    ev = tmp_path / "bank"
    # the second member is an ensemble (a list of checkpoints trained at the same K)
    res = run("laserrl-eval", f"checkpoint={base}", f"bank=[{base},[{tuned},{tuned}]]",
              "eval.K=[0.0,0.1,0.3]", "eval.steps=2", "eval.starts_deg=[-30]", "eval.compile=false",
              f"hydra.run.dir={ev}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    result = json.loads((ev / "eval.json").read_text())
    assert result["bank_K"] == [0.1, 0.0] and result["bank"][1] == [str(tuned), str(tuned)]
    assert set(result["rules"]) == {"single", "nearest", "max_q", "trial"}
    assert result["trial_rule"] == {"steps": 5, "min_rise": 0.002, "lock_r": 0.15}  # conf/eval.yaml's bank_trial
    for rule in result["rules"].values():
        assert list(rule["by_K"]) == ["0", "0.1", "0.3"]
    # nearest K: the fine-tuned model (index 1) at K = 0, the base elsewhere
    assert [v["model"] for v in result["rules"]["nearest"]["by_K"].values()] == [1, 0, 0]
    assert (ev / "generalisation.png").stat().st_size > 0
    # an ensemble of models trained at different K is refused, naming the entry, before any evaluation
    res = run("laserrl-eval", f"bank=[{tuned},[{tuned},{base}]]", "eval.K=[0.0]",
              f"hydra.run.dir={tmp_path / 'bad_bank'}", cwd=tmp_path)
    _one_line_error(res, "bank[1]")
    assert not (tmp_path / "bad_bank" / "eval.json").exists()
    # a scratch_from model that does not record the frames of the models it grew from is refused before training
    import shutil

    unknown = tmp_path / "unknown"
    shutil.copytree(tmp_path / "K+0.00-scratch" / "model", unknown)
    meta = json.loads((unknown / "model.json").read_text())
    del meta["card"]["frames_since_scratch"]
    (unknown / "model.json").write_text(json.dumps(meta))
    res = run("laserrl-train", "experiment=[smoke,transfer_k]", *SMOKE[1:], f"transfer.base={base}",
              f"transfer.scratch_from={unknown}", f"hydra.run.dir={tmp_path / 'refused'}", cwd=tmp_path)
    _one_line_error(res, "transfer.scratch_from")
    assert not (tmp_path / "refused" / "transfer.json").exists()


def test_transfer_rejects_a_non_numeric_K_setting(trained, tmp_path):
    base, _ = trained
    res = run("laserrl-train", "experiment=[smoke,transfer_k]", *SMOKE[1:], f"transfer.base={base}",
              "+transfer.by_K={warm:{stage:{max_steps:3}}}", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    _one_line_error(res, "transfer.by_K")
    assert not (tmp_path / "transfer.json").exists()


def test_transfer_needs_a_base(tmp_path):
    res = run("laserrl-train", "experiment=[smoke,transfer_k]", *SMOKE[1:], f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    _one_line_error(res, "transfer.base")


def test_ray_collector_on_a_local_ray_instance(tmp_path):
    """collector=ray: TorchRL's RayCollector with two actors on a local Ray instance."""
    pytest.importorskip("ray")
    res = run("laserrl-train", *SMOKE, "collector=ray", "collector.num_workers=2", "collector.frames_per_batch=32",
              "collector.ray_num_cpus=2", "collector.memory_gb_per_worker=1", "train.total_frames=96",
              f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    state = torch.load(tmp_path / "checkpoints" / "last.pt", weights_only=False)
    assert state["frames"] == 96 and state["updates"] > 0
    assert (tmp_path / "eval.json").exists()
