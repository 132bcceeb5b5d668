"""Resumable runs (issue: reliability): a real training process killed with SIGKILL and
resumed continues its counters and logs without loss or duplicates; the checkpoint and
replay buffer pair survives a kill at any point; bad checkpoints give one clear error and
change nothing; resume refuses overrides that would change the run."""
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict

from laserrl.agents.dqn import make_replay
from laserrl.checkpoint import CheckpointError
from laserrl.config import ConfigError
from laserrl.resume import RunSaver, load_replay, load_run, resume_config
from laserrl.paths import CONF_DIR

CONF = Path(CONF_DIR)
# a real run, as cheap as it gets: 10 batches of one step of 32 cavities, 2 round trips per step
TINY = ["experiment=smoke", "env.physics.n=64", "env.physics.z_steps=1", "env.max_round_trips=2", "env.num_envs=32",
        "threads=1", "train.progress=false", "logger.backend=csv", "train.total_frames=320",
        "train.checkpoint_every_frames=64"]
BATCH = 32  # experiment=smoke: collector.frames_per_batch


# ----------------------------------------------------------------------------- helpers
def _exe():
    return str(Path(sys.executable).parent / "laserrl-train")


def _start(hydra_dir: Path, *args) -> tuple[subprocess.Popen, Path]:
    """A training process writing into ``hydra_dir`` (its run directory unless args say otherwise)."""
    log = hydra_dir.parent / f"{hydra_dir.name}.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([_exe(), *args, f"hydra.run.dir={hydra_dir}"], cwd=hydra_dir.parent, stdout=out,
                                stderr=subprocess.STDOUT, text=True)
    return proc, log


def _run(hydra_dir: Path, *args):
    return subprocess.run([_exe(), *args, f"hydra.run.dir={hydra_dir}"], cwd=hydra_dir.parent, capture_output=True,
                          text=True, timeout=600)


def _history_frames(run_dir: Path) -> list[int]:
    try:
        return [h["frames"] for h in json.loads((run_dir / "history.json").read_text())]
    except (FileNotFoundError, json.JSONDecodeError):
        return []


def _csv(run_dir: Path, name: str = "train/r_mean") -> list[tuple[int, float]]:
    files = list((run_dir / "logs").glob(f"*/scalars/{name}.csv"))
    if not files:
        return []
    rows = [line.split(",") for line in files[0].read_text().splitlines() if line.strip()]
    return [(int(step), float(value)) for step, value in rows if step and value]


def _wait(proc: subprocess.Popen, condition, what: str, timeout: float = 300.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return
        if proc.poll() is not None:
            pytest.fail(f"training exited (code {proc.returncode}) before {what}")
        time.sleep(0.02)
    proc.kill()
    pytest.fail(f"timed out waiting for {what}")


def _snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file()}


# ----------------------------------------------------------------------------- the real entry point
def test_sigkill_then_resume_continues_counters_and_logs(tmp_path):
    run_dir, whole = tmp_path / "run", tmp_path / "whole"
    victim, _ = _start(run_dir, *TINY)
    reference, _ = _start(whole, *TINY)  # the same run, never interrupted (in parallel)

    def records_after_checkpoint():
        # a periodic checkpoint (history.json comes with it) and a later batch that is not
        # itself a checkpoint batch, so that the kill lands between two checkpoints
        logged, saved = _csv(run_dir), _history_frames(run_dir)
        return bool(saved and logged) and logged[-1][0] > saved[-1] and logged[-1][0] % 64 != 0
    try:
        _wait(victim, records_after_checkpoint, "a checkpoint and later records")
        victim.send_signal(signal.SIGKILL)
        victim.wait(60)
        assert reference.wait(600) == 0
    finally:
        for p in (victim, reference):
            if p.poll() is None:
                p.kill()
                p.wait()
    at_kill = torch.load(run_dir / "checkpoints" / "last.pt", weights_only=False)["frames"]
    assert at_kill >= 64 and at_kill % 64 == 0  # periodic checkpoints only (train.checkpoint_every_frames=64)
    assert _csv(run_dir)[-1][0] > at_kill  # records after the checkpoint exist: they must go

    # a truncated checkpoint: one clear line naming it; the run directory is left as it was
    broken = tmp_path / "broken"
    shutil.copytree(run_dir, broken)
    ckpt = broken / "checkpoints" / "last.pt"
    ckpt.write_bytes(ckpt.read_bytes()[:300])
    before = _snapshot(broken)
    res = _run(tmp_path / "broken-resume", f"resume={broken}")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert f"laserrl-train: error: checkpoint {ckpt} is unreadable" in res.stderr
    assert _snapshot(broken) == before

    # resume; SIGTERM stops it after a batch, with a checkpoint of exactly what was logged
    resumed, log = _start(tmp_path / "resume-1", f"resume={run_dir}")
    try:
        def resumed_records():
            rows = _csv(run_dir)  # read once: the resumed run rewrites the file without the killed run's tail
            return bool(rows) and rows[-1][0] > at_kill + BATCH
        _wait(resumed, resumed_records, "records of the resumed run")
        resumed.send_signal(signal.SIGTERM)
        assert resumed.wait(300) == 128 + signal.SIGTERM
    finally:
        if resumed.poll() is None:
            resumed.kill()
            resumed.wait()
    assert "stopped by SIGTERM" in log.read_text()
    at_term = torch.load(run_dir / "checkpoints" / "last.pt", weights_only=False)["frames"]
    assert at_kill < at_term < 320
    assert _history_frames(run_dir)[-1] == at_term == _csv(run_dir)[-1][0]

    # resume from the checkpoint file, to the end
    res = _run(tmp_path / "resume-2", f"resume={run_dir / 'checkpoints' / 'last.pt'}", "train.progress=false")
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"resuming {run_dir} at {at_term} frames" in res.stdout
    assert f"({at_term} transitions in replay)" in res.stdout  # the buffer came back whole

    summary = json.loads((run_dir / "summary.json").read_text())
    reference_summary = json.loads((whole / "summary.json").read_text())
    assert summary["resumed_at_frames"] == [at_kill, at_term]
    assert (summary["frames"], summary["updates"]) == (reference_summary["frames"], reference_summary["updates"]) == (320, 80)
    history = json.loads((run_dir / "history.json").read_text())
    steps = list(range(BATCH, 321, BATCH))  # every batch exactly once: no gap, no duplicate at either resume
    assert [h["frames"] for h in history] == steps == _history_frames(whole)
    whole_history = json.loads((whole / "history.json").read_text())
    assert [h["updates"] for h in history] == [h["updates"] for h in whole_history]
    # the checkpoints hold the episodes in flight and every generator: the resumed run is the whole run
    for name in ("train/r_mean", "train/loss", "train/round_trips_per_step"):
        assert [h[name] for h in history] == [h[name] for h in whole_history], name
    for name in ("train/r_mean", "train/epsilon", "train/loss"):
        rows = _csv(run_dir, name)
        assert [s for s, _ in rows] == steps
        # what the killed run logged after its checkpoint is gone: every value is the kept run's
        assert [v for _, v in rows] == [h[name] for h in history]
    assert [p.name for p in (run_dir / "checkpoints").iterdir() if p.name.startswith("replay-")] == ["replay-0000000320"]


# ----------------------------------------------------------------------------- checkpoint and buffer pair
def _transitions(start: int, n: int) -> TensorDict:
    idx = torch.arange(start, start + n, dtype=torch.float32)
    return TensorDict({"obs": idx[:, None].expand(n, 3).clone(), "next": {"obs": idx[:, None] + 1.0}}, [n])


def _filled_replay(size=256, frames=100):
    np.random.seed(0)
    replay = make_replay("prioritized", size, 8, alpha=0.7, beta=0.5)
    for start in range(0, frames, 20):
        replay.extend(_transitions(start, 20))
        sample = replay.sample()
        sample["td_error"] = torch.rand(8) * 5
        replay.update_tensordict_priority(sample)
    return replay


def _state(frames: int) -> dict:
    return {"frames": frames, "qnet": {}, "config": {"run_dir": "x"}, "num_actions": 3, "resume": {}}


def _priorities(replay, n):
    tree = replay.sampler._sum_tree
    return [tree[i] for i in range(n)]


def test_an_n_step_run_resumes_with_the_transitions_it_stored(tmp_path):
    run_dir = tmp_path / "run"
    res = _run(run_dir, *TINY, "agent.n_steps=3", "train.total_frames=128")
    assert res.returncode == 0, res.stderr[-3000:]
    state = load_run(run_dir)
    # one step per cavity and batch: the last 3 steps of each cavity still wait for their 3-step returns
    assert state["frames"] == 128 and state["replay_size"] == 128 - 3 * BATCH
    res = _run(tmp_path / "resume", f"resume={run_dir}", "train.total_frames=256")
    assert res.returncode == 0, res.stderr[-3000:]
    state = load_run(run_dir)
    assert state["frames"] == 256 and 0 < state["replay_size"] < 256
    loaded = make_replay("prioritized", 100_000, 8)  # conf/replay: the run's buffer size
    load_replay(loaded, state)
    assert len(loaded) == state["replay_size"]
    assert loaded.storage[: len(loaded)]["steps_to_next_obs"].max() == 3


def test_a_recurrent_run_resumes_with_the_sequences_it_stored(tmp_path):
    run_dir = tmp_path / "run"
    gru = ["env.observation=measured", "env.instruments.spectrum_span=6.0", "env.instruments.spectrum_bins=16",
           "env.instruments.autocorrelation_points=16", "env.gru_size=8", "env.num_envs=8", "collector.frames_per_batch=32",
           "optim.batch_size=16", "replay.init_random_frames=32"]
    res = _run(run_dir, *TINY, *gru, "train.total_frames=64")
    assert res.returncode == 0, res.stderr[-3000:]
    state = load_run(run_dir)
    assert state["frames"] == 64 and state["replay_size"] == 16  # 2 batches x 8 cavities, 4 steps each
    res = _run(tmp_path / "resume", f"resume={run_dir}", "train.total_frames=128")
    assert res.returncode == 0, res.stderr[-3000:]
    state = load_run(run_dir)
    loaded = make_replay("prioritized", 100_000, 16, sequence=4)
    load_replay(loaded, state)
    assert len(loaded) == state["replay_size"] == 32
    stored = loaded.storage[: len(loaded)]
    assert stored.shape == (32, 4) and stored["recurrent_state"].shape == (32, 4, 1, 8)
    # within a stored sequence each step starts from the state the step before left
    assert torch.equal(stored["recurrent_state"][:, 1:], stored["next", "recurrent_state"][:, :-1])


@pytest.mark.parametrize("saved_schedule", [True, False], ids=["schedule-saved", "checkpoint-from-before-schedules"])
def test_the_learning_rate_schedule_continues_across_a_resume(tmp_path, saved_schedule):
    run_dir = tmp_path / "run"
    decay = ["optim.lr=0.001", "optim.lr_decay=0.5", "optim.lr_decay_updates=10"]
    res = _run(run_dir, *TINY, *decay, "train.total_frames=128")
    assert res.returncode == 0, res.stderr[-3000:]
    if not saved_schedule:  # as written before checkpoints held the schedule: counted on from "updates"
        ckpt = run_dir / "checkpoints" / "last.pt"
        state = torch.load(ckpt, weights_only=False)
        del state["resume"]["agent"]["lr_schedule"]
        torch.save(state, ckpt)
    res = _run(tmp_path / "resume", f"resume={run_dir}", "train.total_frames=256")
    assert res.returncode == 0, res.stderr[-3000:]
    history = json.loads((run_dir / "history.json").read_text())
    assert history[-1]["frames"] == 256 and history[-1]["updates"] >= 30  # at least three halvings
    for record in history:  # StepLR, stepped once per update: lr * 0.5 ** (updates // 10), before and after
        assert record["train/lr"] == pytest.approx(0.001 * 0.5 ** (record["updates"] // 10), rel=1e-9)


def test_replay_buffer_comes_back_with_size_and_priorities(tmp_path):
    replay = _filled_replay()
    RunSaver(tmp_path, replay).save(_state(100))
    state = load_run(tmp_path)
    loaded = make_replay("prioritized", 256, 8, alpha=0.7, beta=0.5)
    load_replay(loaded, state)
    assert len(loaded) == len(replay) == 100
    assert _priorities(loaded, 256) == _priorities(replay, 256)
    assert loaded.sampler._max_priority[0] == replay.sampler._max_priority[0]
    assert torch.equal(loaded.storage[:100]["obs"], replay.storage[:100]["obs"])
    np.random.seed(1)
    a = replay.sample()
    np.random.seed(1)
    b = loaded.sample()
    assert torch.equal(a["index"], b["index"]) and torch.equal(a["priority_weight"], b["priority_weight"])
    # only the 100 rows written are on disk, not the 256 allocated
    obs = Path(state["replay_dir"]) / "storage" / "obs.memmap"
    assert obs.stat().st_size == 100 * 3 * 4


def test_a_kill_between_buffer_and_checkpoint_keeps_the_old_pair(tmp_path, monkeypatch):
    replay = _filled_replay(frames=60)
    saver = RunSaver(tmp_path, replay)
    saver.save(_state(60))
    replay.extend(_transitions(60, 40))

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # the process dies after the new buffer is in place, before last.pt
    monkeypatch.setattr("laserrl.resume.save_checkpoint", killed)
    with pytest.raises(KeyboardInterrupt):
        saver.save(_state(100))
    assert (tmp_path / "checkpoints" / "replay-0000000100").is_dir()
    state = load_run(tmp_path)  # still the old pair
    assert state["frames"] == 60 and state["replay_dir"].endswith("replay-0000000060")
    loaded = make_replay("prioritized", 256, 8, alpha=0.7, beta=0.5)
    load_replay(loaded, state)
    assert len(loaded) == 60
    monkeypatch.undo()
    saver.save(_state(100))  # the next save cleans the leftovers
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["last.pt", "replay-0000000100"]


@pytest.mark.parametrize("damage, message", [
    ("missing", "checkpoint not found"),
    ("truncated", "is unreadable"),
    ("foreign", "is not a laserrl checkpoint"),
    ("old", "has no training state to resume"),
    ("no buffer", "which is missing or incomplete"),
    ("saved without buffer", r"saved without its replay buffer \(train.keep_replay=false\)"),
    ("buffer truncated", "replay buffer .* is unreadable"),
])
def test_bad_checkpoints_name_the_path_and_change_nothing(tmp_path, damage, message):
    replay = _filled_replay(frames=40)
    RunSaver(tmp_path, replay).save(_state(40), with_replay=damage != "saved without buffer")
    ckpt, buffer = tmp_path / "checkpoints" / "last.pt", tmp_path / "checkpoints" / "replay-0000000040"
    if damage == "missing":
        ckpt.unlink()
    elif damage == "truncated":
        ckpt.write_bytes(ckpt.read_bytes()[:200])
    elif damage == "foreign":
        torch.save({"weights": torch.zeros(3)}, ckpt)
    elif damage == "old":  # written before checkpoints carried the training state
        state = torch.load(ckpt, weights_only=False)
        del state["resume"]
        torch.save(state, ckpt)
    elif damage == "no buffer":
        shutil.rmtree(buffer)
    elif damage == "buffer truncated":
        (buffer / "sampler" / "sampler_metadata.json").write_text('{"_alpha": 0.7, "_be')
    before = _snapshot(tmp_path)
    with pytest.raises(CheckpointError, match=message) as info:
        load_replay(make_replay("prioritized", 256, 8), load_run(tmp_path))
    assert str(tmp_path) in str(info.value)
    assert _snapshot(tmp_path) == before


# ----------------------------------------------------------------------------- which overrides resume accepts
def _compose(overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


@pytest.fixture(scope="module")
def saved_run():
    saved = OmegaConf.to_container(_compose(["experiment=smoke", "optim.lr=3e-4", "run_dir=/runs/a"]), resolve=True)
    return {"config": saved, "run_dir": "/runs/b"}


def test_resume_keeps_the_saved_config_and_allows_harmless_overrides(saved_run):
    overrides = ["resume=/runs/b", "train.total_frames=1000", "train.max_minutes=3", "optim.lr=3e-4"]
    cfg = resume_config(_compose(overrides), saved_run, overrides)
    assert cfg.train.total_frames == 1000 and cfg.train.max_minutes == 3  # extend a run, give it time
    assert cfg.optim.lr == 3e-4 and cfg.env.num_envs == 8  # the run's own values, not the defaults
    assert cfg.run_dir == "/runs/b" and cfg.resume is None


@pytest.mark.parametrize("override, key", [
    ("optim.lr=1e-2", "optim.lr"), ("seed=3", "seed"), ("stage=duo", "stage"), ("env.num_envs=16", "env.num_envs"),
    ("experiment=smoke", "experiment"), ("logger=csv", "logger"),
])
def test_resume_refuses_overrides_that_change_the_run(saved_run, override, key):
    with pytest.raises(ConfigError, match=rf"^{key}"):
        resume_config(_compose(["resume=/runs/b", override]), saved_run, ["resume=/runs/b", override])
