"""Stable-Baselines3's DQN on the laser cavity, through laserrl's Gymnasium id.

How to run me:

    pip install 'laserrl[sb3]'
    python examples/sb3_dqn.py --timesteps 20000
    python examples/sb3_dqn.py --timesteps 300 --learning-starts 100   # every part in ~2 min; learns nothing yet

It trains DQN on ``laserrl/ModeLock-SISO-v0`` (turn alpha1 in 2 deg steps until the laser
mode-locks, 20 steps per episode), saves the model with ``model.save``, loads it back with
``DQN.load`` and runs one greedy episode, printing its final r = E / M4 (a mode-locked pulse
has r of about 0.2, a plane wave below 0.02).

The env compiles its cavity step (``compile=True``): 20-40 s once, then roughly 0.2 s per
step on a 2-core CPU instead of about 1 s, so 20,000 steps take about an hour.

Only load SB3 zips from sources you trust: unlike laserrl's own models (safetensors and
JSON, which hold no code), an SB3 zip contains pickled Python objects, and ``DQN.load``
unpickles them, which can run arbitrary code.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium
import numpy as np
from stable_baselines3 import DQN

import laserrl  # noqa: F401  registers the laserrl/ModeLock-* ids

ENV_ID = "laserrl/ModeLock-SISO-v0"


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=20_000, help="agent steps to train for")
    parser.add_argument("--out", type=Path, default=Path("sb3_dqn_modelock.zip"), help="where to save the model")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--learning-starts", type=int, default=1_000, help="random steps before the first update")
    parser.add_argument("--no-compile", action="store_true", help="skip torch.compile (slower steps, no start-up)")
    return parser.parse_args(argv)


def train(env: gymnasium.Env, timesteps: int, seed: int, learning_starts: int) -> DQN:
    """DQN with the discount, learning rate and batch size of laserrl-train (``conf/agent/ddqn.yaml``),
    exploration decaying to 0.05 over the first 40 % of the steps (8,000 of 20,000, as there)."""
    # the observation is a Dict (fields, angles): MultiInputPolicy flattens and joins its parts
    model = DQN("MultiInputPolicy", env, learning_rate=1e-3, gamma=0.95, batch_size=64,
                buffer_size=min(timesteps, 50_000),  # a Dict observation is ~4 KB: keep the buffer in RAM
                learning_starts=learning_starts, train_freq=4, target_update_interval=500,
                exploration_fraction=0.4, exploration_final_eps=0.05, seed=seed, device="cpu", verbose=0)
    return model.learn(total_timesteps=timesteps)


def greedy_episode(model: DQN, env: gymnasium.Env, seed: int) -> list[float]:
    """r after every step of one episode of the greedy policy."""
    obs, _ = env.reset(seed=seed)
    r, truncated = [], False
    while not truncated:
        action, _ = model.predict(obs, deterministic=True)
        obs, _, _, truncated, info = env.step(action)
        r.append(info["r"])
    return r


def main(argv=None, env_kwargs: dict | None = None) -> dict:
    """Train, save, load and run one greedy episode; ``env_kwargs`` go to ``gymnasium.make``."""
    args = parse_args(argv)
    env_kwargs = {"compile": not args.no_compile, **(env_kwargs or {})}
    env = gymnasium.make(ENV_ID, **env_kwargs)
    model = train(env, args.timesteps, args.seed, args.learning_starts)
    episode_rewards = [float(ep["r"]) for ep in model.ep_info_buffer]  # the training episodes' returns
    print(f"trained {args.timesteps} steps; mean return of the last episodes: {np.mean(episode_rewards):.3f}")

    model.save(args.out)  # SB3 appends .zip if it is missing
    path = args.out if args.out.suffix == ".zip" else args.out.with_name(args.out.name + ".zip")
    loaded = DQN.load(path, device="cpu")

    r = greedy_episode(loaded, env, seed=args.seed + 1)
    print(f"saved {path}; greedy episode of the loaded model: final r = {r[-1]:.4f}")
    return {"model": model, "loaded": loaded, "path": path, "episode_rewards": episode_rewards, "greedy_r": r}


if __name__ == "__main__":
    main()
