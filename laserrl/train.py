"""``laserrl-train``: double DQN on the batched laser env, configured by Hydra.

Read top to bottom: build the env, the Q-network and TorchRL's DQN parts, collect
with a TorchRL collector, learn from (prioritized) replay, checkpoint, evaluate.

    laserrl-train                                  # paper's single-input task, K = 0.1
    laserrl-train optim.lr=3e-4 env.num_envs=64    # any value from the command line
    laserrl-train logger=csv                        # or tensorboard, none; wandb is offline by default
    laserrl-train resume=outputs/DATE/TIME          # continue a stopped or killed run (laserrl.resume)
"""
from __future__ import annotations

import dataclasses
import math
import random
import sys
import time
from functools import partial
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from laserrl.agents.dqn import (EpsilonSchedule, make_actor, make_exploration_policy, make_loss, make_n_step,
                                make_qnet, make_replay, make_target_updater)
from laserrl.checkpoint import save_json
from laserrl.config import agent_n_steps, check_train_config, log_config, make_logger, optim_lr_decay, user_errors
from laserrl.envs.factory import make_env
from laserrl.resume import (RunCounters, RunInterrupted, RunSaver, StopSignals, env_seed, load_replay, load_run,
                            resume_config, rng_state, set_rng_state)

CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")


def build_agent(cfg: DictConfig, env):
    """Q-network, greedy actor, exploration policy, loss and target updater."""
    spec = env.action_spec_unbatched
    net = cfg.agent.network
    qnet = make_qnet(int(spec.n), cfg.env.physics.n, net.channels, net.kernel_size, net.pool, net.hidden,
                     net.negative_slope)
    actor = make_actor(qnet, spec)
    schedule = EpsilonSchedule(**cfg.agent.exploration)
    policy, egreedy = make_exploration_policy(actor, spec, schedule)
    loss = make_loss(actor, spec, cfg.agent.gamma, cfg.agent.loss_function)
    target = make_target_updater(loss, **cfg.agent.target)
    return qnet, actor, policy, egreedy, schedule, loss, target


def agent_state(loss, lr_schedule, egreedy, target) -> dict:
    """What learning needs beyond the Q-network and the optimizer: the loss module (online and
    target network), the learning-rate schedule, the exploration module's epsilon and a hard
    target update's counter."""
    return {"loss": loss.state_dict(), "lr_schedule": lr_schedule.state_dict(), "egreedy": egreedy.state_dict(),
            "target_counter": getattr(target, "counter", None)}


def load_agent_state(state: dict, loss, optimizer, lr_schedule, egreedy, target) -> None:
    loss.load_state_dict(state["resume"]["agent"]["loss"])
    optimizer.load_state_dict(state["optimizer"])
    if state["resume"]["agent"].get("lr_schedule") is not None:
        lr_schedule.load_state_dict(state["resume"]["agent"]["lr_schedule"])
    else:  # a checkpoint from before the schedule existed: its rate was constant; count on from its updates
        lr_schedule.last_epoch = int(state["updates"])
    egreedy.load_state_dict(state["resume"]["agent"]["egreedy"])
    if state["resume"]["agent"]["target_counter"] is not None:
        target.counter = state["resume"]["agent"]["target_counter"]


def make_collector(cfg: DictConfig, policy, seed: int, frames_done: int = 0):
    """TorchRL collector over the batched env for the frames still to collect after
    ``frames_done`` (None if there are none); ``collector.kind``: sync (one process),
    multi_sync / multi_async (worker processes) or ray (Ray actors, on this machine or a cluster)."""
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
    # The Q-network is feed-forward: it needs no InitTracker or primers, so the collectors
    # must leave the env as it is (torchrl 0.14 warns, and 0.15 would append an InitTracker)
    no_policy_transforms = dict(auto_register_policy_transforms=False)
    if not multi:
        return Collector(env_fn, policy, **common, **no_policy_transforms)
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


def periodic_eval(cfg: DictConfig, actor) -> float:
    """Success rate of the greedy actor under the evaluation protocol (no plots, no files)."""
    from laserrl.evaluate import evaluate_policy

    eval_cfg = {**OmegaConf.to_container(cfg.eval, resolve=True), "plots": False}
    result = evaluate_policy(lambda env: actor, OmegaConf.to_container(cfg.env, resolve=True),
                             OmegaConf.to_container(cfg.stage, resolve=True), eval_cfg, int(cfg.seed))
    return float(result["success_rate"])


def train(cfg: DictConfig, resume: dict | None = None) -> dict:
    """Train, evaluate, checkpoint; returns the evaluation summary.

    The run's checkpoint (``checkpoints/last.pt`` and the replay buffer next to it, see
    ``laserrl.resume``) is written every ``train.checkpoint_every_frames`` frames, at the end, after
    an error between batches, and on SIGTERM or Ctrl-C (which stop the run after the current batch).
    ``resume``: such a checkpoint (``laserrl.resume.load_run``) to continue, with ``cfg`` its config.
    """
    check_train_config(cfg)
    run_dir = Path(cfg.run_dir)
    # the same seed gives the same run on CPU: torch (networks, exploration, uniform replay)
    # and numpy (TorchRL's prioritized sampler draws with np.random); the envs seed their own generators
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    started = time.perf_counter()

    # --- env (only to read specs here; the collector builds its own) and agent
    probe_env = make_env(OmegaConf.to_container(cfg.env, resolve=True), OmegaConf.to_container(cfg.stage, resolve=True),
                         1, cfg.seed, cfg.device)
    qnet, actor, policy, egreedy, schedule, loss, target = build_agent(cfg, probe_env)
    del probe_env
    if cfg.init_from and resume is None:
        from laserrl.warmstart import warm_start

        warm_start(qnet, cfg.init_from, list(cfg.stage.controlled))
        target.init_()  # the target network starts from the warm-started weights
    optimizer = torch.optim.Adam(loss.parameters(), lr=cfg.optim.lr, weight_decay=cfg.optim.weight_decay)
    # stepped once per gradient update: lr * lr_decay ** (updates // lr_decay_updates)
    decay, decay_updates = optim_lr_decay(cfg)
    lr_schedule = torch.optim.lr_scheduler.StepLR(optimizer, step_size=int(decay_updates), gamma=float(decay))
    replay = make_replay(cfg.replay.kind, cfg.replay.size, cfg.optim.batch_size, cfg.replay.alpha, cfg.replay.beta)
    # n-step returns: batches become n-step transitions before they are stored (None: one-step TD)
    n_step = make_n_step(int(agent_n_steps(cfg)), float(cfg.agent.gamma))

    # --- where the run stands: new, or a checkpoint's state (all read before anything is written)
    run = RunCounters(next_eval=cfg.train.get("eval_every_frames") or math.inf)
    if resume is not None:
        run = RunCounters(**resume["resume"]["counters"])
        run.resumed_at_frames.append(run.frames)
        load_agent_state(resume, loss, optimizer, lr_schedule, egreedy, target)
        load_replay(replay, resume)
        started -= run.train_seconds  # train.max_minutes counts the run's earlier invocations too
        print(f"resuming {run_dir} at {run.frames} frames, {run.updates} updates ({len(replay)} transitions in replay)")
    saver = RunSaver(run_dir, replay, resume)
    logger = make_logger(cfg, run_dir, resume["resume"]["logger"] if resume else None, run.frames)
    if logger is not None:
        log_config(logger, cfg)

    def save(with_replay: bool = True) -> Path:
        """Checkpoint (with the replay buffer) and history.json of the run as it stands."""
        run.train_seconds = time.perf_counter() - started
        path = saver.save({
            "qnet": qnet.state_dict(),
            "target": target.loss_module.target_value_network_params.state_dict() if hasattr(target.loss_module, "target_value_network_params") else None,
            "optimizer": optimizer.state_dict(),
            "epsilon": float(egreedy.eps), "frames": run.frames, "updates": run.updates,
            "num_actions": qnet.num_actions, "stage": cfg.stage.name,
            "config": OmegaConf.to_container(cfg, resolve=True),
            "resume": {"agent": agent_state(loss, lr_schedule, egreedy, target), "counters": dataclasses.asdict(run),
                       "rng": rng_state(), "logger": logger.state_dict() if logger is not None else None},
        }, with_replay)
        save_json(run.history, run_dir / "history.json")
        return path

    # --- loop: collect a batch, learn from replay, log, checkpoint now and then
    eval_every = cfg.train.get("eval_every_frames")
    every = cfg.train.get("checkpoint_every_frames")
    next_checkpoint = (run.frames // every + 1) * every if every else math.inf
    max_seconds = 60.0 * cfg.train.max_minutes if cfg.train.max_minutes else math.inf
    bar = tqdm(total=cfg.train.total_frames, initial=run.frames, unit="frames", disable=not cfg.train.progress,
               dynamic_ncols=True)
    target_rate = cfg.train.get("stop_at_success")

    def greedy_success(at_frames: int) -> float:
        success = periodic_eval(cfg, actor)
        if logger is not None:
            logger.log_scalar("eval/success_rate", success, step=at_frames)
        tqdm.write(f"frames {at_frames}: eval success rate {success:.2f}")
        return success

    if eval_every and target_rate is not None and resume is None:
        # a warm-started policy may already meet the target: then it needs no frames at all
        success = greedy_success(0)
        run.history.append({"frames": 0, "updates": 0, "time_s": time.perf_counter() - started, "eval/success_rate": success})
        if success >= target_rate:
            run.frames_to_success = 0
    out_of_time = time.perf_counter() - started > max_seconds
    if out_of_time and run.frames_to_success is None:
        tqdm.write(f"train.max_minutes={cfg.train.max_minutes} already used by this run; raise it to train on")
    # a resumed run's envs start new episodes (their mid-episode state is not saved), seeded from (seed, frames)
    collector = (None if run.frames_to_success is not None or out_of_time
                 else make_collector(cfg, policy, env_seed(cfg.seed, run.frames), run.frames))
    if resume is not None:
        set_rng_state(resume["resume"]["rng"])  # the global generators continue from the checkpoint
    between_batches = True  # the state is that of whole batches: a checkpoint of it is consistent
    try:
        with StopSignals(tqdm.write) as stop:
            for data in (collector if collector is not None else []):
                between_batches = False
                t_batch = time.perf_counter()
                run.frames += data.numel()
                transitions = data if n_step is None else n_step.inv(data)
                if transitions is not None:  # (the first n steps of an n-step run wait for their returns)
                    replay.extend(transitions.reshape(-1))
                egreedy.eps.fill_(schedule(run.frames))
                if run.frames >= cfg.replay.init_random_frames and len(replay) > 0:  # n-step: stored a batch late
                    n_updates = max(1, int(round(data.numel() * cfg.optim.updates_per_frame)))
                    for _ in range(n_updates):
                        sample = replay.sample()
                        losses = loss(sample)
                        optimizer.zero_grad(set_to_none=True)
                        losses["loss"].backward()
                        torch.nn.utils.clip_grad_norm_(loss.parameters(), cfg.optim.max_grad_norm)
                        optimizer.step()
                        lr_schedule.step()
                        target.step()
                        if cfg.replay.kind == "prioritized":
                            replay.update_tensordict_priority(sample)
                        run.updates += 1
                        run.last_loss = float(losses["loss"].detach())
                collector.update_policy_weights_()

                # metrics: raw r (not the centred training reward), final r of finished episodes
                r = data["next", "r"]
                done = data["next", "done"]
                record = {
                    "frames": run.frames, "updates": run.updates, "time_s": time.perf_counter() - started,
                    "train/r_mean": float(r.mean()), "train/loss": run.last_loss, "train/epsilon": float(egreedy.eps),
                    "train/lr": float(optimizer.param_groups[0]["lr"]),
                    "train/round_trips_per_step": float(data["next", "round_trips"].float().mean()),
                }
                if bool(done.any()):
                    record["train/episode_final_r"] = run.last_episode_r = float(r[done].mean())
                record["time/learn_s"] = time.perf_counter() - t_batch
                run.history.append(record)
                if logger is not None:
                    for key, value in record.items():
                        if "/" in key and math.isfinite(value):
                            logger.log_scalar(key, value, step=run.frames)
                between_batches = True
                bar.update(data.numel())
                bar.set_postfix(ep_r=f"{run.last_episode_r:.3f}", r=f"{record['train/r_mean']:.3f}",
                                eps=f"{record['train/epsilon']:.2f}", refresh=False)
                if run.frames >= run.next_eval:  # greedy evaluation during training (the stage's protocol)
                    success = record["eval/success_rate"] = greedy_success(run.frames)
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
            collector.shutdown()
    if stop.signum is not None:
        save()
        raise RunInterrupted(stop.signum, run.frames, str(run_dir))
    ckpt_path = save(with_replay=cfg.train.get("keep_replay", True))

    # --- evaluate, plot
    summary = {"train_seconds": run.train_seconds, "frames": run.frames, "updates": run.updates,
               "checkpoint": str(ckpt_path), "frames_to_success": run.frames_to_success}
    if run.resumed_at_frames:
        summary["resumed_at_frames"] = run.resumed_at_frames
    if cfg.eval.after_training:
        from laserrl.evaluate import evaluate_checkpoint

        result = evaluate_checkpoint(str(ckpt_path), cfg.eval, run_dir)
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
    print(f"checkpoint: {ckpt_path}")
    return summary


def resume_run(cfg: DictConfig) -> dict:
    """``laserrl-train resume=PATH``: continue the run of PATH (its run directory or checkpoint) in
    that directory, with its saved config and those command-line overrides ``resume_config`` allows."""
    from hydra.core.hydra_config import HydraConfig

    state = load_run(cfg.resume)
    return train(resume_config(cfg, state, HydraConfig.get().overrides.task), resume=state)


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="config")
def _hydra_main(cfg: DictConfig) -> float:
    from laserrl.experiments import run_curriculum, run_transfer

    try:
        with user_errors("laserrl-train"):
            if cfg.get("resume"):
                summary = resume_run(cfg)
            elif cfg.get("curriculum"):
                summary = run_curriculum(cfg)
            elif cfg.get("transfer"):
                summary = run_transfer(cfg)
            else:
                summary = train(cfg)
    except RunInterrupted as stop:
        print(f"laserrl-train: {stop}", file=sys.stderr)
        sys.exit(128 + stop.signum)
    metric = summary.get(cfg.metric)
    return float(metric) if metric is not None else float("nan")


def main() -> None:
    _hydra_main()


if __name__ == "__main__":
    main()
