"""The example scripts run end to end (on a small cavity, for a few hundred steps)."""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
# a coarse grid and one round trip per agent step: ~30 ms per step instead of ~1 s
SMALL_CAVITY = dict(physics={"n": 128, "z_steps": 2}, max_round_trips=1, min_round_trips=1, threads=1)


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_sb3_dqn_trains_saves_loads_and_runs_a_greedy_episode(tmp_path, capsys):
    pytest.importorskip("stable_baselines3")
    example = load_example("sb3_dqn")
    out = example.main(["--timesteps", "300", "--learning-starts", "50", "--out", str(tmp_path / "dqn"), "--seed", "1",
                        "--no-compile"], env_kwargs=SMALL_CAVITY)
    assert len(out["episode_rewards"]) == 300 // 20  # SISO episodes last 20 steps
    assert all(math.isfinite(r) for r in out["episode_rewards"])
    assert out["path"] == tmp_path / "dqn.zip" and out["path"].is_file()
    assert len(out["greedy_r"]) == 20 and all(0 < r < 1 for r in out["greedy_r"])
    assert f"final r = {out['greedy_r'][-1]:.4f}" in capsys.readouterr().out
    # the loaded model is the trained one: same Q-values, same greedy actions
    model, loaded = out["model"], out["loaded"]
    env = gymnasium.make(example.ENV_ID, **SMALL_CAVITY)
    observations = [env.reset(seed=s)[0] for s in range(4)] + [env.step(a)[0] for a in (0, 2, 2, 1)]
    for obs in observations:
        with torch.no_grad():
            q_trained = model.q_net(model.policy.obs_to_tensor(obs)[0])
            q_loaded = loaded.q_net(loaded.policy.obs_to_tensor(obs)[0])
        torch.testing.assert_close(q_loaded, q_trained, rtol=0, atol=0)
        assert np.array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
