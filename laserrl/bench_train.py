"""``laserrl-bench --train-loop``: frames per second of the whole training loop.

Each measurement is an ordinary ``laserrl.train.train`` run of ``--train-frames`` frames (the
four-controller task by default, exploration, replay and gradient updates as configured,
no evaluation, no plots, no logger) in a temporary directory. From the run's history:

* **frames / s**: collected frames per second of wall time after the first
  ``--train-warmup-frames`` (the compilation of the cavity step and the random frames before
  learning starts are not counted);
* **learning**: the share of that time spent storing batches and in gradient updates
  (``time/learn_s`` of each batch); **simulation** the rest: the collector stepping the
  cavities, the policy's forward pass and TorchRL's bookkeeping.

Three ways to use the cores are timed in one run, so their ratios hold on a noisy host:
one process with all cores' torch threads (``laserrl-train``'s default, ``threads=null``),
one process with one thread (``threads=1``), and ``--processes`` one-thread processes at
once, as ``laserrl-train -m seed=0,1 hydra/launcher=joblib threads=1`` runs seeds; their
frame rates add up.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

TRAIN_OVERRIDES = ("stage=miso", "stage.K=0.1", "logger=none", "train.progress=false", "train.plots=false",
                   "eval.after_training=false", "train.checkpoint_every_frames=null", "train.keep_replay=false",
                   "train.max_minutes=null")


def loop_rates(history: list[dict], warmup_frames: int) -> dict:
    """Frames per second and the learning share of the batches after ``warmup_frames``."""
    rows = [r for r in history if "time/learn_s" in r]
    start = next((i for i, r in enumerate(rows) if r["frames"] >= warmup_frames), None)
    if start is None or start + 1 >= len(rows):
        raise ValueError(f"the run has no batches after {warmup_frames} warm-up frames; raise --train-frames")
    first, last = rows[start], rows[-1]
    seconds = last["time_s"] - first["time_s"]
    frames = last["frames"] - first["frames"]
    learn = sum(r["time/learn_s"] for r in rows[start + 1:])
    return {"frames": frames, "seconds": seconds, "frames_per_s": frames / seconds, "learn_s": learn,
            "learn_share": learn / seconds, "sim_share": 1.0 - learn / seconds,
            "round_trips_per_step": sum(r["train/round_trips_per_step"] for r in rows[start + 1:]) / (len(rows) - start - 1)}


def train_once(frames: int, threads: int | None, seed: int, overrides: tuple[str, ...], warmup_frames: int) -> dict:
    """One training run of ``frames`` frames with ``threads`` torch threads (None: all cores)."""
    import torch
    from hydra import compose, initialize_config_dir

    from laserrl.paths import CONF_DIR
    from laserrl.train import train

    threads_before = torch.get_num_threads()
    torch.set_num_threads(threads or os.cpu_count() or 1)
    try:
        with tempfile.TemporaryDirectory(prefix="laserrl-bench-") as run_dir:
            with initialize_config_dir(str(CONF_DIR), version_base=None):
                cfg = compose("config", overrides=[*TRAIN_OVERRIDES, *overrides, f"train.total_frames={frames}",
                                                   f"seed={seed}", f"threads={threads or 'null'}",
                                                   f"run_dir={run_dir}"])
            train(cfg)
            history = json.loads((Path(run_dir) / "history.json").read_text())
    finally:
        torch.set_num_threads(threads_before)
    return loop_rates(history, warmup_frames)


def _worker(frames, seed, overrides, warmup_frames, barrier, results) -> None:
    try:
        import torch

        torch.set_num_threads(1)
        barrier.wait(timeout=900)
        results.put(("ok", train_once(frames, 1, seed, overrides, warmup_frames)))
    except BaseException as err:  # noqa: BLE001 - reported by the parent, which raises
        barrier.abort()
        results.put(("error", f"{type(err).__name__}: {err}"))


def train_in_processes(processes: int, frames: int, overrides: tuple[str, ...], warmup_frames: int) -> list[dict]:
    """``processes`` one-thread training runs at once (seeds 0, 1, ...), spawned and started on a barrier."""
    from laserrl.spawned import spawn_on_barrier

    return spawn_on_barrier(_worker, [(frames, seed, overrides, warmup_frames) for seed in range(processes)], 3600,
                            "training benchmark")


def print_train_loop(frames: int, processes: int, overrides: tuple[str, ...], warmup_frames: int) -> dict:
    """Time the three ways of using the cores and print the table; returns the measurements."""
    cores = os.cpu_count() or 1
    print(f"training loop: {frames} frames per run ({', '.join(TRAIN_OVERRIDES[:2] + tuple(overrides))}), "
          f"counted after {warmup_frames} frames")
    rows = [(f"1 process, {cores} threads (threads=null)", [train_once(frames, None, 0, overrides, warmup_frames)]),
            ("1 process, 1 thread (threads=1)", [train_once(frames, 1, 0, overrides, warmup_frames)])]
    if processes > 1:
        rows.append((f"{processes} processes x 1 thread at once", train_in_processes(processes, frames, overrides,
                                                                                   warmup_frames)))
    base = rows[0][1][0]["frames_per_s"]
    print()
    print("| cores used as | frames / s (sum) | x threads=null | simulation | learning | round trips / step |")
    print("|---|---:|---:|---:|---:|---:|")
    out = []
    for name, runs in rows:
        fps = sum(r["frames_per_s"] for r in runs)
        sim = sum(r["sim_share"] for r in runs) / len(runs)
        rts = sum(r["round_trips_per_step"] for r in runs) / len(runs)
        print(f"| {name} | {fps:,.1f} | {fps / base:.2f} | {sim:.0%} | {1 - sim:.0%} | {rts:.1f} |")
        out.append({"name": name, "frames_per_s": fps, "sim_share": sim, "runs": runs})
    best = max(out, key=lambda r: r["frames_per_s"])
    if not math.isclose(best["frames_per_s"], base):
        print(f"\nfastest: {best['name']}, {best['frames_per_s'] / base:.2f}x the default")
    return {"rows": out}
