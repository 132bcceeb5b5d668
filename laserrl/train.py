"""``laserrl-train``: double DQN on the batched laser env, configured by Hydra.

Read top to bottom: build the env, the Q-network and TorchRL's DQN parts, collect
with a TorchRL collector, learn from (prioritized) replay, evaluate, save.

    laserrl-train                                  # paper's single-input task, K = 0.1
    laserrl-train optim.lr=3e-4 env.num_envs=64    # any value from the command line
    laserrl-train logger=csv                        # or tensorboard, none; wandb is offline by default
"""
from __future__ import annotations

import json
import math
import time
from functools import partial
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from laserrl.agents.dqn import (EpsilonSchedule, make_actor, make_exploration_policy, make_loss, make_qnet,
                                make_replay, make_target_updater)
from laserrl.checkpoint import save_checkpoint
from laserrl.config import check_train_config, log_config, make_logger, user_errors
from laserrl.envs.factory import make_env

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


def make_collector(cfg: DictConfig, policy, seed: int):
    """TorchRL collector over the batched env; ``collector.kind``: sync (one process),
    multi_sync / multi_async (worker processes) or ray (Ray actors, on this machine or a cluster)."""
    from torchrl.collectors import Collector, MultiAsyncCollector, MultiSyncCollector

    multi = cfg.collector.kind != "sync"
    # a partial of plain dicts pickles, so spawned workers can rebuild the env
    env_fn = partial(make_env, OmegaConf.to_container(cfg.env, resolve=True),
                     OmegaConf.to_container(cfg.stage, resolve=True), cfg.env.num_envs, seed, cfg.device,
                     threads=cfg.collector.worker_threads if multi else None)
    common = dict(frames_per_batch=cfg.collector.frames_per_batch, total_frames=cfg.train.total_frames,
                  init_random_frames=cfg.replay.init_random_frames, device=cfg.device)
    if not multi:
        return Collector(env_fn, policy, **common)
    if cfg.collector.kind == "ray":
        from torchrl.collectors.distributed import RayCollector

        # one Collector per Ray actor, each stepping its own batch of env.num_envs cavities
        return RayCollector([env_fn] * int(cfg.collector.num_workers), policy, sync=bool(cfg.collector.sync),
                            collector_class=Collector,
                            ray_init_config={"address": cfg.collector.ray_address,
                                             "num_cpus": cfg.collector.ray_num_cpus, "ignore_reinit_error": True},
                            remote_configs={"num_cpus": cfg.collector.cpus_per_worker,
                                            "memory": int(cfg.collector.memory_gb_per_worker * 1024**3)},
                            **common)
    cls = MultiSyncCollector if cfg.collector.kind == "multi_sync" else MultiAsyncCollector
    return cls([env_fn] * int(cfg.collector.num_workers), policy, **common)


def periodic_eval(cfg: DictConfig, actor) -> float:
    """Success rate of the greedy actor under the evaluation protocol (no plots, no files)."""
    from laserrl.evaluate import evaluate_policy

    eval_cfg = {**OmegaConf.to_container(cfg.eval, resolve=True), "plots": False}
    result = evaluate_policy(lambda env: actor, OmegaConf.to_container(cfg.env, resolve=True),
                             OmegaConf.to_container(cfg.stage, resolve=True), eval_cfg, int(cfg.seed))
    return float(result["success_rate"])


def train(cfg: DictConfig) -> dict:
    """Train, evaluate, checkpoint; returns the evaluation summary."""
    check_train_config(cfg)
    run_dir = Path(cfg.run_dir)
    # the same seed gives the same run on CPU: torch (networks, exploration, uniform replay)
    # and numpy (TorchRL's prioritized sampler draws with np.random); the envs seed their own generators
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    started = time.perf_counter()

    # --- env (only to read specs here; the collector builds its own) and agent
    probe_env = make_env(OmegaConf.to_container(cfg.env, resolve=True), OmegaConf.to_container(cfg.stage, resolve=True),
                         1, cfg.seed, cfg.device)
    qnet, actor, policy, egreedy, schedule, loss, target = build_agent(cfg, probe_env)
    del probe_env
    if cfg.init_from:
        from laserrl.warmstart import warm_start

        warm_start(qnet, cfg.init_from, list(cfg.stage.controlled))
        target.init_()  # the target network starts from the warm-started weights
    optimizer = torch.optim.Adam(loss.parameters(), lr=cfg.optim.lr, weight_decay=cfg.optim.weight_decay)
    replay = make_replay(cfg.replay.kind, cfg.replay.size, cfg.optim.batch_size, cfg.replay.alpha, cfg.replay.beta)
    collector = make_collector(cfg, policy, cfg.seed)
    logger = make_logger(cfg, run_dir)
    if logger is not None:
        log_config(logger, cfg)

    # --- loop: collect a batch, learn from replay, log
    history: list[dict] = []
    frames = updates = 0
    eval_every = cfg.train.get("eval_every_frames")
    next_eval = eval_every or math.inf
    frames_to_success = None
    max_seconds = 60.0 * cfg.train.max_minutes if cfg.train.max_minutes else math.inf
    bar = tqdm(total=cfg.train.total_frames, unit="frames", disable=not cfg.train.progress, dynamic_ncols=True)
    last_loss = last_episode_r = float("nan")
    target_rate = cfg.train.get("stop_at_success")

    def greedy_success(at_frames: int) -> float:
        success = periodic_eval(cfg, actor)
        if logger is not None:
            logger.log_scalar("eval/success_rate", success, step=at_frames)
        tqdm.write(f"frames {at_frames}: eval success rate {success:.2f}")
        return success

    if eval_every and target_rate is not None:
        # a warm-started policy may already meet the target: then it needs no frames at all
        success = greedy_success(0)
        history.append({"frames": 0, "updates": 0, "time_s": time.perf_counter() - started, "eval/success_rate": success})
        if success >= target_rate:
            frames_to_success = 0
    for data in ([] if frames_to_success == 0 else collector):
        t_batch = time.perf_counter()
        frames += data.numel()
        replay.extend(data.reshape(-1))
        egreedy.eps.fill_(schedule(frames))
        if frames >= cfg.replay.init_random_frames:
            n_updates = max(1, int(round(data.numel() * cfg.optim.updates_per_frame)))
            for _ in range(n_updates):
                sample = replay.sample()
                losses = loss(sample)
                optimizer.zero_grad(set_to_none=True)
                losses["loss"].backward()
                torch.nn.utils.clip_grad_norm_(loss.parameters(), cfg.optim.max_grad_norm)
                optimizer.step()
                target.step()
                if cfg.replay.kind == "prioritized":
                    replay.update_tensordict_priority(sample)
                updates += 1
                last_loss = float(losses["loss"].detach())
        collector.update_policy_weights_()

        # metrics: raw r (not the centred training reward), final r of finished episodes
        r = data["next", "r"]
        done = data["next", "done"]
        record = {
            "frames": frames, "updates": updates, "time_s": time.perf_counter() - started,
            "train/r_mean": float(r.mean()), "train/loss": last_loss, "train/epsilon": float(egreedy.eps),
            "train/round_trips_per_step": float(data["next", "round_trips"].float().mean()),
        }
        if bool(done.any()):
            record["train/episode_final_r"] = last_episode_r = float(r[done].mean())
        record["time/learn_s"] = time.perf_counter() - t_batch
        history.append(record)
        if logger is not None:
            for key, value in record.items():
                if "/" in key and math.isfinite(value):
                    logger.log_scalar(key, value, step=frames)
        bar.update(data.numel())
        bar.set_postfix(ep_r=f"{last_episode_r:.3f}", r=f"{record['train/r_mean']:.3f}",
                        eps=f"{record['train/epsilon']:.2f}", refresh=False)
        if frames >= next_eval:  # greedy evaluation during training (the stage's protocol)
            next_eval += eval_every
            success = record["eval/success_rate"] = greedy_success(frames)
            if target_rate is not None and success >= target_rate:
                frames_to_success = frames
                tqdm.write(f"success rate {success:.2f} >= train.stop_at_success={target_rate} after {frames} frames; stopping")
                break
        if time.perf_counter() - started > max_seconds:
            tqdm.write(f"train.max_minutes={cfg.train.max_minutes} reached after {frames} frames; stopping")
            break
    bar.close()
    collector.shutdown()
    train_seconds = time.perf_counter() - started

    # --- save, evaluate, plot
    ckpt_path = run_dir / "checkpoints" / "last.pt"
    save_checkpoint({
        "qnet": qnet.state_dict(),
        "target": target.loss_module.target_value_network_params.state_dict() if hasattr(target.loss_module, "target_value_network_params") else None,
        "optimizer": optimizer.state_dict(),
        "epsilon": float(egreedy.eps), "frames": frames, "updates": updates,
        "num_actions": qnet.num_actions, "stage": cfg.stage.name,
        "config": OmegaConf.to_container(cfg, resolve=True),
    }, ckpt_path)
    (run_dir / "history.json").write_text(json.dumps(history))
    summary = {"train_seconds": train_seconds, "frames": frames, "updates": updates, "checkpoint": str(ckpt_path),
               "frames_to_success": frames_to_success}
    if cfg.eval.after_training:
        from laserrl.evaluate import evaluate_checkpoint

        result = evaluate_checkpoint(str(ckpt_path), cfg.eval, run_dir)
        summary.update({f"eval/{k}": v for k, v in result.items() if not isinstance(v, (list, dict))})
        if logger is not None:
            for k in ("success_rate", "mean_final_reward", "mean_steps_to_lock"):
                if result.get(k) is not None and math.isfinite(result[k]):
                    logger.log_scalar(f"eval/{k}", result[k], step=frames)
    if cfg.train.plots:
        from laserrl.plots import plot_training

        plot_training(history, run_dir / "training_curves.png")
    summary["time/total_s"] = time.perf_counter() - started
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if logger is not None and hasattr(logger, "experiment") and cfg.logger.backend == "wandb":
        logger.experiment.finish()
    print(f"checkpoint: {ckpt_path}")
    return summary


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="config")
def _hydra_main(cfg: DictConfig) -> float:
    from laserrl.experiments import run_curriculum, run_transfer

    with user_errors("laserrl-train"):
        if cfg.get("curriculum"):
            summary = run_curriculum(cfg)
        elif cfg.get("transfer"):
            summary = run_transfer(cfg)
        else:
            summary = train(cfg)
    metric = summary.get(cfg.metric)
    return float(metric) if metric is not None else float("nan")


def main() -> None:
    _hydra_main()


if __name__ == "__main__":
    main()
