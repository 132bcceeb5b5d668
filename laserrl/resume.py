"""Resumable training runs: the checkpoint and replay buffer pair, and ``laserrl-train resume=PATH``.

A run directory holds, next to the logs::

    checkpoints/last.pt              networks, target network, optimizer, loss and exploration state,
                                     counters, history, logger state, RNG states, config
    checkpoints/replay-0000012800/   the replay buffer at frame 12800, TorchRL's ``ReplayBuffer.dumps``
                                     (storage, prioritized sampler with its priorities, writer)

``RunSaver.save`` writes a pair in three steps: the buffer into ``replay-F.tmp``, renamed to
``replay-F``; ``last.pt`` naming ``replay-F`` (written to a temp file, then renamed); older
buffers removed. A kill at any point leaves ``last.pt`` naming a complete buffer of the same
moment: the old pair until ``last.pt`` is replaced, the new one after.

The environments are not continued exactly: TorchRL's collector does not save the state of
running environments (the cavities' fields and angles mid-episode), so a resumed run starts
new episodes, from environments seeded with ``env_seed(seed, frames)``.
"""
from __future__ import annotations

import os
import random
import shutil
import signal
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from laserrl.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from laserrl.config import ConfigError

REPLAY_PREFIX = "replay-"

#: Overrides that ``resume`` accepts with a new value: they change how long or how visibly the
#: run goes on, not what it learns. Any other key must keep the run's saved value.
RESUME_OVERRIDES = ("train.total_frames", "train.max_minutes", "train.checkpoint_every_frames", "train.keep_replay",
                    "train.progress", "train.plots", "eval.after_training", "eval.plots", "eval.compile", "env.compile",
                    "threads", "collector.worker_threads", "metric")


@dataclass
class RunCounters:
    """Where a run stands; saved in every checkpoint. ``train_seconds``: collection and learning
    time so far (``train.max_minutes`` counts it over all invocations of the run)."""

    frames: int = 0
    updates: int = 0
    next_eval: float = float("inf")
    frames_to_success: int | None = None
    history: list = field(default_factory=list)
    last_loss: float = float("nan")
    last_episode_r: float = float("nan")
    train_seconds: float = 0.0
    resumed_at_frames: list = field(default_factory=list)
    best: dict | None = None  # train.keep_best: frames, success_rate, mean_final_reward of the kept weights


def env_seed(seed: int, frames: int) -> int:
    """Seed of the collector's environments: ``seed`` for a new run, a well-mixed function of
    (seed, frames) for a run resumed at ``frames`` (so it does not replay its first episodes)."""
    if frames == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), int(frames)]).generate_state(1)[0])


def rng_state() -> dict:
    """States of the global generators: torch (networks, exploration, uniform replay), numpy
    (TorchRL's prioritized sampler) and Python's ``random``, as tensors and plain numbers (what
    ``torch.load(weights_only=True)`` reads back)."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(),
            "numpy": {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                      "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
            "python": random.getstate()}


def set_rng_state(state: Mapping[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached_gaussian"]))
    random.setstate(state["python"])


# ----------------------------------------------------------------------------- replay buffer on disk
class FilledRows:
    """Save and load hooks of TorchRL's storage checkpointer: dump only the rows written so far
    (the storage is allocated at ``replay.size`` rows, mostly empty early in a run: 8 KB per row
    at n = 256) and pad back to the full size on load. The writer's cursor and the sampler's
    priorities are saved by TorchRL as usual."""

    def __init__(self, storage):
        self.storage = storage

    def save(self, data, path=None):
        n = len(self.storage)
        return data if n >= data.shape[0] else data[:n]

    def load(self, data, out=None):
        size = self.storage.max_size
        if data.shape[0] == size:
            return data
        full = data.new_zeros((size, *data.shape[1:])) if out is None else out  # rows of a recurrent agent's sequences
        full[: data.shape[0]] = data
        return full


def compact_dumps(replay):
    """Register ``FilledRows`` on a replay buffer (once; TorchRL does not save hooks)."""
    if not getattr(replay, "_laserrl_compact", False):
        hooks = FilledRows(replay.storage)
        replay.register_save_hook(hooks.save)
        replay.register_load_hook(hooks.load)
        replay._laserrl_compact = True
    return replay


class RunSaver:
    """Writes consistent (checkpoint, replay buffer) pairs into ``run_dir/checkpoints``."""

    def __init__(self, run_dir: str | os.PathLike, replay, saved: Mapping[str, Any] | None = None):
        self.dir = Path(run_dir) / "checkpoints"
        self.path = self.dir / "last.pt"
        self.replay = compact_dumps(replay)
        # the buffer the current last.pt names, and the frame count it was written at
        self.replay_name = saved.get("replay") if saved else None
        self.saved_frames = saved.get("frames") if saved else None

    def save(self, state: dict, with_replay: bool = True) -> Path:
        """Save ``state`` (with ``frames``) and, unless ``with_replay`` is false, the replay buffer;
        returns the checkpoint path. A checkpoint without its buffer cannot be resumed."""
        frames = int(state["frames"])
        name = f"{REPLAY_PREFIX}{frames:010d}" if len(self.replay) and with_replay else None
        self.dir.mkdir(parents=True, exist_ok=True)
        if name is not None and name != self.replay_name:  # the buffer only changes with new frames
            tmp = self.dir / f"{name}.tmp"
            shutil.rmtree(tmp, ignore_errors=True)
            self.replay.dumps(tmp)
            # TorchRL pickles its prefetch queue (empty here: no prefetch); the loader refuses pickles
            (tmp / "prefetch.pkl").unlink(missing_ok=True)
            shutil.rmtree(self.dir / name, ignore_errors=True)  # an unreferenced leftover of a killed run
            os.replace(tmp, self.dir / name)
        # the transitions stored: with n-step returns fewer than the frames (the last n steps wait for their returns)
        save_checkpoint({**state, "replay": name, "replay_size": len(self.replay) if name else 0}, self.path)
        self.replay_name, self.saved_frames = name, frames
        for old in self.dir.glob(f"{REPLAY_PREFIX}*"):
            if old.name != name:
                shutil.rmtree(old, ignore_errors=True)
        return self.path


def load_run(path: str | os.PathLike) -> dict:
    """The checkpoint of a run to resume (``path``: its run directory or checkpoint file), with
    ``run_dir`` and ``replay_dir`` added. Raises ``CheckpointError`` naming the path if anything
    needed is missing or unreadable; reads only."""
    state = load_checkpoint(Path(path).absolute())
    ckpt = Path(state["path"])
    if "resume" not in state:
        raise CheckpointError(f"checkpoint {ckpt} has no training state to resume (not written by a resumable "
                              f"laserrl-train); use it with init_from= to warm-start a new run instead")
    state["run_dir"] = str(ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent)
    state["replay_dir"] = None
    if state.get("replay"):
        replay_dir = ckpt.parent / state["replay"]
        if not (replay_dir / "buffer_metadata.json").is_file():
            raise CheckpointError(f"checkpoint {ckpt} names the replay buffer {replay_dir}, which is missing or incomplete")
        check_replay_files(replay_dir)
        state["replay_dir"] = str(replay_dir)
    elif state["frames"] > 0:
        raise CheckpointError(f"checkpoint {ckpt} was saved without its replay buffer (train.keep_replay=false), so "
                              f"the run cannot continue; use it with init_from= to warm-start a new run instead")
    return state


#: what a replay buffer directory written by laserrl holds: memory-mapped arrays and JSON
REPLAY_SUFFIXES = (".memmap", ".json")


def check_replay_files(replay_dir: Path) -> None:
    """Refuse a replay buffer directory holding anything but memory-mapped arrays and JSON:
    TorchRL's loader would unpickle some other files (a prefetch queue, non-tensor fields),
    which can run code."""
    for path in sorted(Path(replay_dir).rglob("*")):
        if path.is_file() and path.suffix not in REPLAY_SUFFIXES:
            raise CheckpointError(f"replay buffer {replay_dir} holds {path.relative_to(replay_dir)}, which laserrl "
                                  "does not load (only .memmap arrays and .json; other files can run code). If you "
                                  "wrote this run yourself with an older laserrl, delete that file and resume again")


def load_replay(replay, state: Mapping[str, Any]) -> None:
    """Fill ``replay`` from the buffer a checkpoint of ``load_run`` names (nothing if none)."""
    if not state.get("replay_dir"):
        return
    try:
        compact_dumps(replay).loads(state["replay_dir"])
    except Exception as err:  # truncated memmaps or json fail in many ways inside torchrl
        raise CheckpointError(f"replay buffer {state['replay_dir']} is unreadable "
                              f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None
    # checkpoints from before replay_size was recorded stored one transition per frame
    expected = int(state.get("replay_size", min(int(state["frames"]), int(replay.storage.max_size))))
    if len(replay) != expected:
        raise CheckpointError(f"replay buffer {state['replay_dir']} holds {len(replay)} transitions; "
                              f"its checkpoint expects {expected}")


# ----------------------------------------------------------------------------- the config of a resumed run
def resume_config(cfg: DictConfig, state: Mapping[str, Any], overrides: Sequence[str]) -> DictConfig:
    """The saved config of the run, with the command line's ``overrides`` that ``RESUME_OVERRIDES``
    allows; any other override must repeat the saved value, or a ``ConfigError`` names it."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    saved = OmegaConf.create(state["config"])
    changes = {}
    for override in OverridesParser.create().parse_overrides(list(overrides)):
        key = override.key_or_group
        if key == "resume" or key.startswith("hydra"):
            continue
        if key in ("experiment", "sweep"):  # they set keys all over the config: not checkable one by one
            raise ConfigError(f"{key}={override.value()} cannot be combined with resume: the run continues with its "
                              f"saved config (give single keys, e.g. train.total_frames=...)")
        new, old = _plain(OmegaConf.select(cfg, key)), _plain(OmegaConf.select(saved, key))
        if new == old:
            continue
        if key not in RESUME_OVERRIDES:
            raise ConfigError(f"{key} cannot change when resuming (the run has {old!r}, given {new!r}); "
                              f"keys that can: {', '.join(RESUME_OVERRIDES)}")
        changes[key] = new
    for key, value in changes.items():
        OmegaConf.update(saved, key, value, force_add=True)
    saved.run_dir = state["run_dir"]
    saved.resume = None
    return saved


def _plain(value):
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


# ----------------------------------------------------------------------------- stopping on request
class RunInterrupted(Exception):
    """The run was stopped by a signal after checkpointing; ``laserrl-train resume=RUN_DIR`` continues it."""

    def __init__(self, signum: int, frames: int, run_dir: str):
        self.signum = signum
        super().__init__(f"stopped by {signal.Signals(signum).name} at {frames} frames; checkpoint saved, "
                         f"continue with: laserrl-train resume={run_dir}")


class StopSignals:
    """While active, SIGTERM (clusters, ``kill``) or a first Ctrl-C only ask the training loop to stop
    after the current batch, so that it can checkpoint a consistent state; a second Ctrl-C
    interrupts at once. Signal handlers exist only in the main thread; elsewhere this does nothing."""

    def __init__(self, notify=print):
        self.signum: int | None = None
        self.notify = notify
        self._previous: dict = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.signum is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signum = signum
        self.notify(f"{signal.Signals(signum).name}: stopping after this batch to checkpoint (Ctrl-C again: stop now)")

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()
        return False
