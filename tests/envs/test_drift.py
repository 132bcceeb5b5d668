"""K moving within an episode: the random walk stays in its range, jumps redraw it, both are
seeded by the env, and evaluation holds K still."""
import pytest
import torch

from laserrl.envs.laser_env import LaserCavityEnv
from laserrl.envs.step import drift_K

FAST = dict(max_round_trips=2, min_round_trips=1)


def test_walk_reflects_into_the_range_and_jumps_redraw():
    g = torch.Generator().manual_seed(0)
    K = torch.full((4000,), 0.39, dtype=torch.float64)
    walked = drift_K(K, -0.2, 0.4, 0.05, 0.0, g)
    assert float(walked.min()) >= -0.2 and float(walked.max()) <= 0.4
    # the walk K + sigma xi, folded back at 0.4: the same draws of xi by hand
    free = 0.39 + 0.05 * torch.randn(4000, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert (free > 0.4).any() and torch.allclose(walked, torch.where(free > 0.4, 0.8 - free, free))
    assert torch.allclose(drift_K(torch.tensor([0.45], dtype=torch.float64), -0.2, 0.4, 0.0, 0.0), torch.tensor([0.35],
                          dtype=torch.float64))  # reflected
    jumped = drift_K(K, -0.2, 0.4, 0.0, 0.25, torch.Generator().manual_seed(1))
    moved = jumped != K
    assert 0.22 < float(moved.double().mean()) < 0.28  # the jump probability
    assert float(jumped[moved].mean()) == pytest.approx(0.1, abs=0.02)  # uniform redraws over the range


def test_env_moves_K_each_step_inside_its_range_and_is_seeded():
    def Ks(seed):
        env = LaserCavityEnv(8, K=[-0.2, 0.4], K_drift=0.02, K_jump=0.1, seed=seed, **FAST)
        env.reset()
        out = [env.K]
        for _ in range(5):
            env.rand_step()
            out.append(env.K)
        return torch.stack(out)

    a, b, c = Ks(3), Ks(3), Ks(4)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert float(a.min()) >= -0.2 and float(a.max()) <= 0.4
    assert bool((a[1:] != a[:-1]).all())


def test_drift_needs_a_range_and_valid_numbers():
    with pytest.raises(ValueError, match="K_drift and K_jump move K within a range"):
        LaserCavityEnv(1, K=0.1, K_drift=0.01)
    with pytest.raises(ValueError, match="K_jump must be a probability"):
        LaserCavityEnv(1, K=[0.0, 0.1], K_jump=1.5)
    with pytest.raises(ValueError, match="K_drift must be >= 0"):
        LaserCavityEnv(1, K=[0.0, 0.1], K_drift=-0.1)


def test_evaluation_holds_K_at_each_value_of_the_grid():
    from laserrl.evaluate import evaluate_policy

    env_cfg = {"max_round_trips": 2, "min_round_trips": 1, "tol": None, "dtype": "complex64", "compile": False,
               "physics": {"n": 64, "z_steps": 2}}
    stage = {"controlled": ["alpha1"], "steps_deg": [2.0], "K": [-0.2, 0.4], "K_drift": 0.05, "K_jump": 0.5,
             "max_steps": 3, "init_angles_deg": {"alpha1": -20.0, "alpha2": 3.0, "alpha3": 28.0, "alpha_p": 88.0}}
    seen = []

    def policy_for(env):
        def hold(td):
            seen.append(env.K)
            return td.set("action", torch.ones(td.batch_size, dtype=torch.int64))
        return hold

    evaluate_policy(policy_for, env_cfg, stage, {"K": [0.05, 0.3], "steps": 3, "success_r": 0.15}, seed=0)
    assert all(torch.equal(K, torch.tensor([0.05, 0.3], dtype=torch.float64)) for K in seen)
