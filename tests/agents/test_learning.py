"""The DDQN pipeline learns: after a small budget, the greedy policy ends episodes with
a higher reward than a random policy on the same starts (the paper's r, which the agent reading
measured signals is not given: it is trained on the readings' own reward).

The paper's cavity with only 5 round trips per agent step and starts in [-40, -34] deg,
where the laser is mode-locked but r rises towards alpha1 ~ -24 deg: the agent has to
learn to turn alpha1 the right way and stop there; a random walk stays near its start."""
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import RandomPolicy

from laserrl.envs.factory import make_env
from laserrl.envs.laser_env import reset_at
from laserrl.train import train
from laserrl.paths import CONF_DIR

CONF = Path(CONF_DIR)
STARTS = [-40.0, -38.0, -36.0, -34.0]


@pytest.mark.parametrize("variant", [
    ["agent.n_steps=1"],  # one-step TD (the paper)
    ["agent.n_steps=3"],  # n-step returns
    # what instruments read (no fields), the last two readings stacked, the readings' reward
    ["agent.n_steps=1", "env.observation=measured", "env.history=2"],
    # what instruments read, remembered by a GRU trained on sequences of 8 steps (16 cavities x 8)
    ["agent.n_steps=1", "env.observation=measured", "env.gru_size=32", "collector.frames_per_batch=128"],
    # the same with the additive Q-head (V + one value per move of the angle)
    ["agent.n_steps=1", "env.observation=measured", "env.gru_size=32", "collector.frames_per_batch=128",
     "agent.network.head=additive"],
], ids=["one-step", "n-step", "measured-history", "measured-gru", "measured-gru-additive"])
def test_greedy_policy_beats_random_policy(tmp_path, variant):
    overrides = ["collector.frames_per_batch=64", *variant,
        f"run_dir={tmp_path}", "seed=0", "logger=none", "env.compile=false", "env.num_envs=16",
        "env.max_round_trips=5", "stage.init_angles_deg.alpha1=[-40,-34]", "stage.max_steps=8",
        "train.total_frames=2048", "train.progress=false", "train.plots=false",
        "replay.init_random_frames=256", "optim.batch_size=64",
        "optim.updates_per_frame=0.5", "optim.lr=1e-3", "agent.gamma=0.9",
        "agent.exploration.decay_frames=500", "agent.exploration.end=0.05",
        "agent.network.channels=[8,8]", "agent.network.pool=4", "agent.network.hidden=[64]",
        f"eval.starts_deg={STARTS}", "eval.steps=8", "eval.plots=false",
    ]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    summary = train(cfg)
    learned = summary["eval/mean_final_reward"]

    # random policy, same protocol: same starts, same number of steps, raw r
    env = make_env(OmegaConf.to_container(cfg.env, resolve=True), OmegaConf.to_container(cfg.stage, resolve=True),
                   len(STARTS) * 4, seed=1, centred=False, max_steps=8)
    init = torch.deg2rad(torch.tensor([[a, 3.0, 28.0, 88.0] for a in STARTS] * 4, dtype=torch.float64))
    td = reset_at(env, TensorDict(init_angles=init, batch_size=[len(init)]))  # through a history transform too
    torch.manual_seed(1)
    rollout = env.rollout(8, RandomPolicy(env.action_spec), auto_reset=False, tensordict=td)
    random_final = float(rollout["next", "r"][:, -1].mean())

    print(f"greedy mean final r {learned:.4f}, random {random_final:.4f}")
    assert learned > random_final + 0.02, (learned, random_final)
