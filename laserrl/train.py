"""``laserrl-train``: double DQN on the batched laser env, configured by Hydra.

Read ``train`` top to bottom: seed, build the agent (``DQNAgent``: TorchRL's DQN parts) and
its replay, restore a checkpoint when resuming, then collect batches with a TorchRL
collector, store them, take gradient steps (``DQNAgent.update``), log (``batch_record``),
evaluate now and then (``greedy_success``) and checkpoint (``save_run``); ``finish``
evaluates the final checkpoint. The Hydra entry point is ``laserrl.cli``.

    laserrl-train                                  # paper's single-input task, K = 0.1
    laserrl-train optim.lr=3e-4 env.num_envs=64    # any value from the command line
    laserrl-train logger=csv                        # or tensorboard, none; wandb is offline by default
    laserrl-train resume=outputs/DATE/TIME          # continue a stopped or killed run (laserrl.resume)
"""
from __future__ import annotations

import dataclasses
import functools
import math
import random
import shlex
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from tqdm import tqdm

from laserrl.agents.dqn import DQNAgent, make_n_step, make_replay
from laserrl.checkpoint import save_json
from laserrl.model import git_commit, model_metadata, package_version, save_model, update_model_meta
from laserrl.config import (agent_n_steps, check_device, check_logger_config, log_config, make_logger,
                            optim_lr_decay)
from laserrl.envs.factory import make_env
from laserrl.envs.laser_env import LaserCavityEnv, base_env_of
from laserrl.evaluate import check_eval_config
from laserrl.resume import (RunCounters, RunInterrupted, RunSaver, StopSignals, env_seed, load_replay, load_run,
                            resume_config, rng_state, set_rng_state)
from laserrl.validate import ConfigError, check_number, check_numbers, check_one_of


@dataclass(frozen=True)
class LoopSettings:
    """The training loop's own numbers: the frame budget and its safety-net time limit, how often
    to evaluate and checkpoint, when to stop at a success rate, gradient steps per frame and
    the random frames before learning starts."""

    total_frames: int
    updates_per_frame: float
    init_random_frames: int
    max_minutes: float | None = None
    eval_every_frames: int | None = None
    stop_at_success: float | None = None
    checkpoint_every_frames: int | None = None
    keep_best: bool = False
    reselect_top: int | None = None

    def __post_init__(self):
        check_number(self.total_frames, "train.total_frames", low=1, integer=True)
        check_number(self.max_minutes, "train.max_minutes", low=0, low_open=True, optional=True)
        check_number(self.eval_every_frames, "train.eval_every_frames", low=1, integer=True, optional=True)
        check_number(self.stop_at_success, "train.stop_at_success", low=0, high=1, optional=True)
        check_number(self.checkpoint_every_frames, "train.checkpoint_every_frames", low=1, integer=True, optional=True)
        check_number(self.updates_per_frame, "optim.updates_per_frame", low=0, low_open=True)
        check_number(self.init_random_frames, "replay.init_random_frames", low=0, integer=True)
        if not isinstance(self.keep_best, bool):
            raise ConfigError(f"train.keep_best must be true or false, got {self.keep_best!r}")
        if self.keep_best and not self.eval_every_frames:
            raise ConfigError("train.keep_best needs train.eval_every_frames (the evaluations that choose the weights)")
        check_number(self.reselect_top, "train.reselect.top", low=2, integer=True, optional=True)
        if self.reselect_top is not None and not self.keep_best:
            raise ConfigError("train.reselect needs train.keep_best=true (it validates again the best-validated weights)")

    @classmethod
    def from_config(cls, cfg: DictConfig) -> "LoopSettings":
        t = cfg.train
        return cls(t.total_frames, cfg.optim.updates_per_frame, cfg.replay.init_random_frames, t.get("max_minutes"),
                   t.get("eval_every_frames"), t.get("stop_at_success"), t.get("checkpoint_every_frames"),
                   t.get("keep_best", False), reselect_settings(cfg)[0])


def reselect_settings(cfg: DictConfig) -> tuple[int | None, dict]:
    """``train.reselect``: (top, the eval overrides of its second validation), or (None, {}) when off."""
    r = cfg.train.get("reselect")
    if r is None:
        return None, {}
    if not isinstance(r, DictConfig) or "top" not in r or "repeats" not in r:
        raise ConfigError(f"train.reselect must be null or {{top: N, repeats: R, K: [...] or null}}, got {r!r}")
    unknown = set(r) - {"top", "repeats", "K"}
    if unknown:
        raise ConfigError(f"train.reselect has unknown keys {sorted(unknown)} (top, repeats, K)")
    check_number(r.repeats, "train.reselect.repeats", low=1, integer=True)
    K = r.get("K")
    K = check_numbers(OmegaConf.to_container(K) if isinstance(K, ListConfig) else K, "train.reselect.K",
                      optional=True, scalar_ok=True)
    return r.top, {"repeats": int(r.repeats), **({"K": K} if K is not None else {})}


def check_collector_config(c: DictConfig) -> None:
    """The ``collector`` config's own values (rules that involve other groups: ``check_train_config``)."""
    check_one_of(c.kind, "collector.kind", ("sync", "multi_sync", "multi_async", "ray"))
    check_number(c.frames_per_batch, "collector.frames_per_batch", low=1, integer=True)
    check_number(c.num_workers, "collector.num_workers", low=1, integer=True)
    check_number(c.get("worker_threads"), "collector.worker_threads", low=1, integer=True, optional=True)


def check_train_config(cfg: DictConfig):
    """Everything a run will build, built once on a dry run before anything is written: each
    builder and dataclass checks its own values (its errors name the config key); checked here
    are only the top-level keys and the rules that involve several groups. Returns the env's
    unbatched action spec (what the run's agent is built for)."""
    check_number(cfg.seed, "seed", low=0, high=2**32 - 1, integer=True)  # numpy's seed range
    check_number(cfg.threads, "threads", low=1, integer=True, optional=True)
    check_device(cfg.device)
    check_collector_config(cfg.collector)
    check_logger_config(cfg)
    LoopSettings.from_config(cfg)
    stage = OmegaConf.to_container(cfg.stage, resolve=True)
    # the eval.* left null take the stage's protocol
    check_eval_config(OmegaConf.to_container(cfg.eval, resolve=True), stage.get("protocol"))
    env = make_env(OmegaConf.to_container(cfg.env, resolve=True), stage, cfg.env.num_envs, cfg.seed, cfg.device)
    build_agent(cfg, env.action_spec_unbatched)
    n_steps = make_n_step(agent_n_steps(cfg), cfg.agent.gamma)
    # rules across groups
    c, num_envs = cfg.collector, int(cfg.env.num_envs)
    if c.frames_per_batch % num_envs:
        raise ConfigError(f"collector.frames_per_batch ({c.frames_per_batch}) must be a multiple of "
                          f"env.num_envs ({num_envs})")
    if cfg.env.get("gru_size") is not None:
        if replay_sequence(cfg) < 2:
            raise ConfigError(f"env.gru_size: a recurrent agent learns from sequences of collector.frames_per_batch / "
                              f"env.num_envs steps, here {replay_sequence(cfg)}; raise collector.frames_per_batch")
        if n_steps is not None:
            raise ConfigError("env.gru_size: a recurrent agent learns from one-step targets; set agent.n_steps=1")
        if c.kind != "sync":
            raise ConfigError(f"env.gru_size: a recurrent agent is trained with collector=sync, not {c.kind}")
    make_replay(cfg.replay.kind, cfg.replay.size, cfg.optim.batch_size, cfg.replay.alpha, cfg.replay.beta,
                sequence=replay_sequence(cfg))
    if c.kind == "ray" and c.sync:
        share, left = divmod(c.frames_per_batch, int(c.num_workers))
        if left or share % num_envs:
            raise ConfigError(f"collector.frames_per_batch ({c.frames_per_batch}) must split over "
                              f"collector.num_workers ({c.num_workers}) into multiples of env.num_envs ({num_envs})")
    if n_steps is not None and (c.kind == "multi_async" or (c.kind == "ray" and not c.sync)):
        # n-step returns join each batch to the previous one, which needs the same envs in the same order
        raise ConfigError(f"agent.n_steps={cfg.agent.n_steps} needs batches from every env in turn: use "
                          f"collector=sync, multi_sync or ray with collector.sync=true, not {c.kind}"
                          + (" with sync=false" if c.kind == "ray" else ""))
    return env.action_spec_unbatched


def replay_sequence(cfg: DictConfig) -> int:
    """Steps per replay item: one (a transition) for a feed-forward agent; for a recurrent one
    (``env.gru_size``) a collector batch's row, the ``frames_per_batch / num_envs`` steps of one cavity."""
    return 1 if cfg.env.get("gru_size") is None else int(cfg.collector.frames_per_batch) // int(cfg.env.num_envs)


def build_agent(cfg: DictConfig, action_spec) -> DQNAgent:
    """The double DQN of the ``agent`` and ``optim`` config for an env with ``action_spec``."""
    decay, decay_updates = optim_lr_decay(cfg)
    return DQNAgent.build(action_spec, OmegaConf.to_container(cfg.env, resolve=True), network=cfg.agent.network,
                          exploration=dict(cfg.agent.exploration), gamma=cfg.agent.gamma,
                          loss_function=cfg.agent.loss_function, target=dict(cfg.agent.target), lr=cfg.optim.lr,
                          weight_decay=cfg.optim.weight_decay, lr_decay=decay, lr_decay_updates=decay_updates,
                          max_grad_norm=cfg.optim.max_grad_norm, prioritized=cfg.replay.kind == "prioritized",
                          average_decay=cfg.agent.get("average_decay"))


def seed_everything(cfg: DictConfig) -> None:
    """The same seed gives the same run on CPU: torch (networks, exploration, uniform replay) and
    numpy (TorchRL's prioritized sampler draws with np.random); the envs seed their own generators."""
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))


def make_collector(cfg: DictConfig, policy, seed: int, frames_done: int = 0, envs: dict | None = None):
    """TorchRL collector over the batched env for the frames still to collect after
    ``frames_done`` (None if there are none); ``collector.kind``: sync (one process),
    multi_sync / multi_async (worker processes) or ray (Ray actors, on this machine or a cluster).
    ``envs``: a sync collector's env ``snapshot`` from a checkpoint, whose episodes it continues."""
    from torchrl.collectors import Collector, MultiAsyncCollector, MultiSyncCollector

    if cfg.train.total_frames <= frames_done:
        return None
    multi = cfg.collector.kind != "sync"
    # a partial of plain dicts pickles, so spawned workers can rebuild the env
    env_fn = partial(make_env, OmegaConf.to_container(cfg.env, resolve=True),
                     OmegaConf.to_container(cfg.stage, resolve=True), cfg.env.num_envs, seed, cfg.device,
                     threads=cfg.collector.worker_threads if multi else None)
    common = dict(frames_per_batch=cfg.collector.frames_per_batch, total_frames=cfg.train.total_frames - frames_done,
                  init_random_frames=max(0, cfg.replay.init_random_frames - frames_done), device=cfg.device)
    # make_env adds what a recurrent Q-network needs (env.gru_size: InitTracker and its primer), so
    # the collectors must leave the env as it is (torchrl 0.14 warns, and 0.15 would append an InitTracker)
    no_policy_transforms = dict(auto_register_policy_transforms=False)
    if not multi:
        return Collector(partial(env_fn, snapshot=envs), policy, **common, **no_policy_transforms)
    if cfg.collector.kind == "ray":
        from torchrl.collectors.distributed import RayCollector

        # one Collector per Ray actor, each stepping its own batch of env.num_envs cavities
        return RayCollector([env_fn] * int(cfg.collector.num_workers), policy, sync=bool(cfg.collector.sync),
                            collector_class=Collector, collector_kwargs=no_policy_transforms,
                            ray_init_config={"address": cfg.collector.ray_address,
                                             "num_cpus": cfg.collector.ray_num_cpus, "ignore_reinit_error": True},
                            remote_configs={"num_cpus": cfg.collector.cpus_per_worker,
                                            "memory": int(cfg.collector.memory_gb_per_worker * 1024**3)},
                            **common)
    cls = MultiSyncCollector if cfg.collector.kind == "multi_sync" else MultiAsyncCollector
    return cls([env_fn] * int(cfg.collector.num_workers), policy, **common, **no_policy_transforms)


def greedy_success(cfg: DictConfig, actor, frames: int, logger, seed: int | None = None,
                   overrides: dict | None = None, name: str = "eval/success_rate") -> tuple[float, float]:
    """Periodic evaluation (validation): the success rate and mean final r of the greedy actor
    under the stage's protocol (``cfg.eval`` with ``overrides``) with the run's seed (or ``seed``;
    no plots, no files), logged as ``name`` at ``frames``."""
    from laserrl.evaluate import evaluate_policy

    eval_cfg = {**OmegaConf.to_container(cfg.eval, resolve=True), **(overrides or {}), "plots": False, "seed": None}
    result = evaluate_policy(lambda env: actor, OmegaConf.to_container(cfg.env, resolve=True),
                             OmegaConf.to_container(cfg.stage, resolve=True), eval_cfg,
                             int(cfg.seed if seed is None else seed))
    success, final_r = float(result["success_rate"]), float(result["mean_final_reward"])
    if logger is not None:
        logger.log_scalar(name, success, step=frames)
    tqdm.write(f"frames {frames}: {name} {success:.2f}, mean final r {final_r:.4f}")
    return success, final_r


def validation_score(entry: dict) -> tuple[float, float]:
    """How validations rank weights: success rate, then mean final r."""
    return entry["success_rate"], entry["mean_final_reward"]


def keep_if_best(run: RunCounters, agent: DQNAgent, best_weights: dict, success: float, final_r: float,
                 finalists: list | None = None, top: int | None = None) -> None:
    """``train.keep_best``: keep the Q-network's weights if they did better on the validation than
    the kept ones (higher success rate; at equal success, higher mean final r). With
    ``train.reselect`` (``top``), also keep the ``top`` best-validated weights in ``finalists``
    (best first) for ``reselect``."""
    entry = {"frames": run.frames, "success_rate": success, "mean_final_reward": final_r}
    finalist = top is not None and finalists is not None and (
        len(finalists) < top or validation_score(entry) > validation_score(finalists[-1]))
    best = run.best is None or validation_score(entry) > validation_score(run.best)
    if not (finalist or best):
        return
    weights = {k: v.detach().clone() for k, v in agent.model_weights().items()}  # one copy for both
    if finalist:
        finalists.append({**entry, "weights": weights})
        finalists.sort(key=validation_score, reverse=True)  # stable: at equal scores the earlier weights first
        del finalists[top:]
    if best:
        run.best = entry
        best_weights.clear()
        best_weights.update(weights)


def reselect(cfg: DictConfig, agent: DQNAgent, run: RunCounters, best_weights: dict, finalists: list, logger) -> None:
    """``train.reselect``: the best of a few noisy validations is partly luck (the best of many
    estimates overstates its weights), so the ``top`` best-validated weights are validated again on
    a wider draw (``train.reselect.K`` x ``repeats``, noise seed: the run's seed + 2, neither the
    validation's nor the final evaluation's) and the best there is kept; ``run.best`` records both."""
    _, overrides = reselect_settings(cfg)
    greedy = agent.greedy_qnet
    current = {k: v.detach().clone() for k, v in greedy.state_dict().items()}
    scores = []
    try:
        for f in finalists:
            greedy.load_state_dict(f["weights"])
            success, final_r = greedy_success(cfg, agent.greedy, f["frames"], None, seed=int(cfg.seed) + 2,
                                              overrides=overrides, name="eval/reselect_success_rate")
            scores.append({"frames": f["frames"], "success_rate": success, "mean_final_reward": final_r,
                           "validation": validation_score(f)})
    finally:
        greedy.load_state_dict(current)  # the training state stays that of the last weights
    i = max(range(len(scores)), key=lambda j: validation_score(scores[j]))  # ties: the better validated
    chosen = finalists[i]
    run.best = {"frames": chosen["frames"], "success_rate": chosen["success_rate"],
                "mean_final_reward": chosen["mean_final_reward"],
                "reselect": {"success_rate": scores[i]["success_rate"], "mean_final_reward": scores[i]["mean_final_reward"],
                             "finalists": scores}}
    best_weights.clear()
    best_weights.update(chosen["weights"])
    if logger is not None:
        logger.log_scalar("eval/reselect_chosen_frames", float(chosen["frames"]), step=run.frames)


def env_snapshot(collector) -> dict | None:
    """The state of a sync collector's cavities (episodes in flight); None for collectors whose
    envs live in other processes, whose state TorchRL cannot hand over."""
    base = base_env_of(getattr(collector, "env", None))
    return base.snapshot() if isinstance(base, LaserCavityEnv) else None


def save_run(saver: RunSaver, agent: DQNAgent, run: RunCounters, cfg: DictConfig, logger, started: float,
             envs=lambda: None, best_weights: dict | None = None, finalists: list | None = None,
             with_replay: bool = True) -> Path:
    """Checkpoint the run as it stands (with the replay buffer unless ``with_replay`` is false,
    and the collector's episodes in flight, ``envs()``) and rewrite its history.json; returns
    the checkpoint path."""
    run.train_seconds = time.perf_counter() - started
    config = OmegaConf.to_container(cfg, resolve=True)
    path = saver.save({
        "qnet": agent.qnet.state_dict(), "target": agent.target_weights(), "optimizer": agent.optimizer.state_dict(),
        "epsilon": float(agent.egreedy.eps), "frames": run.frames, "updates": run.updates,
        "num_actions": agent.qnet.num_actions, "stage": cfg.stage.name,
        "config": config, **({"best_qnet": best_weights} if best_weights else {}),
        **({"finalists": finalists} if finalists else {}),
        **({"averaged_qnet": agent.model_weights()} if agent.averaged is not None else {}),
        "resume": {"agent": agent.learning_state(), "counters": dataclasses.asdict(run), "rng": rng_state(),
                   "logger": logger.state_dict() if logger is not None else None, "envs": envs()},
    }, with_replay)
    save_model(Path(cfg.run_dir) / "model", best_weights or agent.model_weights(),
               model_metadata(config, agent.qnet.num_actions, frames=run.frames,
                              best=run.best, card=model_card(cfg, run)), replace=True)
    save_json(run.history, Path(cfg.run_dir) / "history.json")
    return path


def model_card(cfg: DictConfig, run: RunCounters) -> dict:
    """How the run's model came about: the command (when run by laserrl-train), the commit of
    the code, the machine, the date, frames and training time."""
    import datetime

    from laserrl.model import machine_line

    try:
        from hydra.core.hydra_config import HydraConfig

        overrides = list(HydraConfig.get().overrides.task)
        command = " ".join(["laserrl-train", *(shlex.quote(o) for o in overrides)])
    except ValueError:  # not run by the Hydra app
        command = None
    before = warm_start_frames(cfg.init_from) if cfg.init_from else 0
    return {"command": command, "commit": git_commit(), "laserrl_version": package_version(), "machine": machine_line(),
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"), "seed": int(cfg.seed),
            "frames": run.frames, "episodes": run.frames // int(cfg.stage.max_steps), "train_seconds": round(run.train_seconds, 1),
            "resumed_at_frames": list(run.resumed_at_frames),
            # with the frames of the models it was warm-started from (a curriculum's earlier stages)
            "frames_since_scratch": None if before is None else before + run.frames}


@functools.lru_cache(maxsize=8)
def warm_start_frames(init_from: str) -> int | None:
    """``laserrl.model.frames_since_scratch`` of the model a run was warm-started from (None if unknown)."""
    from laserrl.checkpoint import CheckpointError
    from laserrl.model import frames_since_scratch, load_model

    try:
        return frames_since_scratch(load_model(init_from))
    except CheckpointError:
        return None


def store(replay, n_step, data, sequences: bool = False) -> None:
    """Put a collected batch (cavities, steps) into replay: as transitions, n-step ones when
    ``n_step`` is set (their first n steps wait in the transform until their returns are
    complete), or with ``sequences`` (a recurrent agent) each cavity's steps as one item."""
    if sequences:
        replay.extend(data.reshape(-1, data.shape[-1]))
        return
    transitions = data if n_step is None else n_step.inv(data)
    if transitions is not None:
        replay.extend(transitions.reshape(-1))


def batch_record(data, run: RunCounters, agent: DQNAgent, started: float, t_batch: float) -> dict:
    """The metrics of one batch: raw r (not the centred training reward) and the final r of the
    episodes that ended in it."""
    r, done = data["next", "r"], data["next", "done"]
    record = {
        "frames": run.frames, "updates": run.updates, "time_s": time.perf_counter() - started,
        "train/r_mean": float(r.mean()), "train/loss": run.last_loss, "train/epsilon": float(agent.egreedy.eps),
        "train/lr": agent.lr, "train/round_trips_per_step": float(data["next", "round_trips"].float().mean()),
    }
    if bool(done.any()):
        record["train/episode_final_r"] = run.last_episode_r = float(r[done].mean())
    record["time/learn_s"] = time.perf_counter() - t_batch
    return record


def log_record(logger, record: dict, frames: int) -> None:
    if logger is None:
        return
    for key, value in record.items():
        if "/" in key and math.isfinite(value):
            logger.log_scalar(key, value, step=frames)


def train(cfg: DictConfig, resume: dict | None = None) -> dict:
    """Train, evaluate, checkpoint; returns the evaluation summary.

    The run's checkpoint (``checkpoints/last.pt`` and the replay buffer next to it, see
    ``laserrl.resume``) is written every ``train.checkpoint_every_frames`` frames, at the end, after
    an error between batches, and on SIGTERM or Ctrl-C (which stop the run after the current batch).
    ``resume``: such a checkpoint (``laserrl.resume.load_run``) to continue, with ``cfg`` its config.
    """
    action_spec = check_train_config(cfg)
    loop = LoopSettings.from_config(cfg)
    run_dir = Path(cfg.run_dir)
    seed_everything(cfg)
    git_commit()  # the code this process runs: its model card names this commit
    started = time.perf_counter()

    # --- the agent, its replay and n-step transform
    agent = build_agent(cfg, action_spec)
    if cfg.init_from and resume is None:
        from laserrl.warmstart import warm_start

        warm_start(agent.qnet, cfg.init_from, list(cfg.stage.controlled))
        agent.target.init_()  # the target network starts from the warm-started weights
        agent.restart_average()
    replay = make_replay(cfg.replay.kind, cfg.replay.size, cfg.optim.batch_size, cfg.replay.alpha, cfg.replay.beta,
                         sequence=replay_sequence(cfg))
    n_step = make_n_step(int(agent_n_steps(cfg)), float(cfg.agent.gamma))  # None: one-step TD
    sequences = replay_sequence(cfg) > 1  # a recurrent agent stores each cavity's steps of a batch together

    # --- where the run stands: new, or a checkpoint's state (all read before anything is written)
    run = RunCounters(next_eval=loop.eval_every_frames or math.inf)
    if resume is not None:
        run = RunCounters(**resume["resume"]["counters"])
        run.resumed_at_frames.append(run.frames)
        agent.load_learning_state(resume["resume"]["agent"], resume["optimizer"], resume["updates"])
        load_replay(replay, resume)
        started -= run.train_seconds  # train.max_minutes counts the run's earlier invocations too
        print(f"resuming {run_dir} at {run.frames} frames, {run.updates} updates ({len(replay)} transitions in replay)")
    saver = RunSaver(run_dir, replay, resume)
    logger = make_logger(cfg, run_dir, resume["resume"]["logger"] if resume else None, run.frames)
    if logger is not None:
        log_config(logger, cfg)
    collector, envs_at_shutdown = None, None
    # train.keep_best: the weights that did best on the periodic validation (saved with the run)
    best_weights = dict(resume["best_qnet"]) if resume is not None and "best_qnet" in resume else {}
    # train.reselect: the best few validated weights, validated again at the end
    finalists = list(resume.get("finalists", [])) if resume is not None else []
    keep = partial(keep_if_best, run, agent, best_weights, finalists=finalists, top=loop.reselect_top)
    save = partial(save_run, saver, agent, run, cfg, logger, started,
                   lambda: env_snapshot(collector) if collector is not None else envs_at_shutdown, best_weights,
                   finalists)

    # --- budgets: frames decide; train.max_minutes is a safety net
    eval_every, every, target_rate = loop.eval_every_frames, loop.checkpoint_every_frames, loop.stop_at_success
    next_checkpoint = (run.frames // every + 1) * every if every else math.inf
    max_seconds = 60.0 * loop.max_minutes if loop.max_minutes else math.inf
    if eval_every and resume is None and (target_rate is not None or (loop.keep_best and cfg.init_from)):
        # a warm-started policy may already meet the target: then it needs no frames at all; and with
        # train.keep_best its weights are a candidate, so that fine-tuning cannot end worse than it began
        success, final_r = greedy_success(cfg, agent.greedy, 0, logger)
        if loop.keep_best:
            keep(success, final_r)
        run.history.append({"frames": 0, "updates": 0, "time_s": time.perf_counter() - started, "eval/success_rate": success})
        if target_rate is not None and success >= target_rate:
            run.frames_to_success = 0
    out_of_time = time.perf_counter() - started > max_seconds
    if out_of_time and run.frames_to_success is None:
        tqdm.write(f"train.max_minutes={cfg.train.max_minutes} already used by this run; raise it to train on")
    # a resumed run continues the episodes in flight where the checkpoint holds them (sync collector);
    # otherwise its envs start new episodes, seeded from (seed, frames)
    saved_envs = resume["resume"].get("envs") if resume is not None else None
    if run.frames_to_success is None and not out_of_time:
        collector = make_collector(cfg, agent.policy, env_seed(cfg.seed, run.frames), run.frames, saved_envs)
    if resume is not None:
        set_rng_state(resume["resume"]["rng"])  # the global generators continue from the checkpoint

    # --- the loop: collect a batch, store it, learn from replay, log, evaluate and checkpoint now and then
    bar = tqdm(total=loop.total_frames, initial=run.frames, unit="frames", disable=not cfg.train.progress,
               dynamic_ncols=True)
    between_batches = True  # the state is that of whole batches: a checkpoint of it is consistent
    try:
        with StopSignals(tqdm.write) as stop:
            for data in (collector if collector is not None else []):
                between_batches = False
                t_batch = time.perf_counter()
                run.frames += data.numel()
                store(replay, n_step, data, sequences)
                agent.explore(run.frames)
                if run.frames >= loop.init_random_frames and len(replay) > 0:  # n-step: stored a batch late
                    for _ in range(max(1, int(round(data.numel() * loop.updates_per_frame)))):
                        run.last_loss = agent.update(replay)
                        run.updates += 1
                collector.update_policy_weights_()
                record = batch_record(data, run, agent, started, t_batch)
                run.history.append(record)
                log_record(logger, record, run.frames)
                between_batches = True
                bar.update(data.numel())
                bar.set_postfix(ep_r=f"{run.last_episode_r:.3f}", r=f"{record['train/r_mean']:.3f}",
                                eps=f"{record['train/epsilon']:.2f}", refresh=False)
                if run.frames >= run.next_eval:  # greedy evaluation during training (the stage's protocol)
                    success, final_r = greedy_success(cfg, agent.greedy, run.frames, logger)
                    record["eval/success_rate"] = success
                    if loop.keep_best:
                        keep(success, final_r)
                    run.next_eval += eval_every
                    if target_rate is not None and success >= target_rate:
                        run.frames_to_success = run.frames
                        tqdm.write(f"success rate {success:.2f} >= train.stop_at_success={target_rate} after "
                                   f"{run.frames} frames; stopping")
                        break
                if run.frames >= next_checkpoint:
                    save()
                    next_checkpoint += every
                if stop.signum is not None:
                    break
                if time.perf_counter() - started > max_seconds:
                    tqdm.write(f"train.max_minutes={cfg.train.max_minutes} reached after {run.frames} frames; stopping")
                    break
    except BaseException:
        if between_batches and run.frames != (saver.saved_frames or 0):
            tqdm.write(f"checkpoint of the last whole batch: {save()}")
        raise
    finally:
        bar.close()
        if collector is not None:
            envs_at_shutdown = env_snapshot(collector)  # the collector lets go of its env on shutdown
            collector.shutdown()
            collector = None
    if stop.signum is not None:
        save()
        raise RunInterrupted(stop.signum, run.frames, str(run_dir))
    if loop.keep_best and not (run.history and run.history[-1].get("eval/success_rate") is not None):
        keep(*greedy_success(cfg, agent.greedy, run.frames, logger))  # the last weights
    if loop.reselect_top is not None and finalists and "reselect" not in (run.best or {}):
        reselect(cfg, agent, run, best_weights, finalists, logger)
    ckpt_path = save(with_replay=cfg.train.get("keep_replay", True))
    if run.best is not None:
        print(f"the model keeps the weights of frame {run.best['frames']} (validation success "
              f"{run.best['success_rate']:.2f}, mean final r {run.best['mean_final_reward']:.4f}"
              + (f"; validated again: {run.best['reselect']['success_rate']:.2f}" if "reselect" in run.best else "")
              + ")")
    summary = finish(cfg, run, ckpt_path, logger, started)
    print(f"checkpoint: {ckpt_path}")
    return summary


def finish(cfg: DictConfig, run: RunCounters, ckpt_path: Path, logger, started: float) -> dict:
    """After training: evaluate the checkpoint with the stage's protocol, plot, write summary.json."""
    run_dir = Path(cfg.run_dir)
    model = run_dir / "model"
    summary = {"train_seconds": run.train_seconds, "frames": run.frames, "updates": run.updates,
               "checkpoint": str(ckpt_path), "model": str(model), "frames_to_success": run.frames_to_success}
    if run.resumed_at_frames:
        summary["resumed_at_frames"] = run.resumed_at_frames
    if run.best is not None:
        summary["best"] = run.best
    if cfg.eval.after_training:
        from laserrl.evaluate import evaluate_checkpoint

        eval_cfg = OmegaConf.to_container(cfg.eval, resolve=True)
        if eval_cfg.get("seed") is None and run.best is not None:
            eval_cfg["seed"] = int(cfg.seed) + 1  # fresh draws: not those that chose the weights
        result = evaluate_checkpoint(str(model), eval_cfg, run_dir)
        update_model_meta(model, eval={k: v for k, v in result.items() if k != "per_start"})
        summary.update({f"eval/{k}": v for k, v in result.items() if not isinstance(v, (list, dict))})
        if logger is not None:
            for k in ("success_rate", "mean_final_reward", "mean_steps_to_lock"):
                if result.get(k) is not None and math.isfinite(result[k]):
                    logger.log_scalar(f"eval/{k}", result[k], step=run.frames)
    if cfg.train.plots:
        from laserrl.plots import plot_training

        plot_training(run.history, run_dir / "training_curves.png")
    summary["time/total_s"] = time.perf_counter() - started
    save_json(summary, run_dir / "summary.json", indent=2)
    if logger is not None and hasattr(logger, "experiment") and cfg.logger.backend == "wandb":
        logger.experiment.finish()
    return summary


def resume_run(cfg: DictConfig) -> dict:
    """``laserrl-train resume=PATH``: continue the run of PATH (its run directory or checkpoint) in
    that directory, with its saved config and those command-line overrides ``resume_config`` allows."""
    from hydra.core.hydra_config import HydraConfig

    state = load_run(cfg.resume)
    return train(resume_config(cfg, state, HydraConfig.get().overrides.task), resume=state)
