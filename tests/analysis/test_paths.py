"""Angle paths: the straight comparison path, and replays that reproduce the env's rollouts."""
import pytest
import torch
from tensordict import TensorDict

from laserrl.analysis import StepSettings, follow_paths, full_angles, straight_path
from laserrl.envs import LaserCavityEnv, deltas_to_action
from laserrl.physics import CavityParams


def test_straight_path_interpolates_from_start_to_end():
    path = straight_path([-15.0, -3.0], [-21.0, 3.0], 3)
    assert torch.allclose(path, torch.tensor([[-17.0, -1.0], [-19.0, 1.0], [-21.0, 3.0]], dtype=torch.float64))
    long = straight_path([-15.0, -3.0], [-21.0, 4.0], 40)
    steps = torch.diff(torch.cat([torch.tensor([[-15.0, -3.0]], dtype=torch.float64), long]), dim=0)
    assert long.shape == (40, 2) and torch.allclose(long[-1], torch.tensor([-21.0, 4.0], dtype=torch.float64))
    assert torch.allclose(steps, steps[0].expand_as(steps))  # equal steps along one line
    assert torch.equal(straight_path([1.0], [2.0], 1), torch.tensor([[2.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="steps"):
        straight_path([0.0], [1.0], 0)
    with pytest.raises(ValueError, match="same number"):
        straight_path([0.0, 1.0], [1.0], 2)


def test_full_angles_fills_in_the_fixed_plates():
    out = full_angles([[1.0, 2.0], [3.0, 4.0]], ["alpha1", "alpha3"], {"alpha1": 0, "alpha2": 9, "alpha3": 0, "alpha_p": 8})
    assert out.tolist() == [[1.0, 9.0, 2.0, 8.0], [3.0, 9.0, 4.0, 8.0]]


def test_replayed_paths_reproduce_the_env_rollout():
    params = CavityParams(n=64, z_steps=2)  # any physics will do: the replay must match it exactly
    env = LaserCavityEnv(2, params=params, controlled=("alpha1", "alpha2"), steps_deg=(2.0, 2.0), max_round_trips=5,
                         init_angles_deg={"alpha1": -20.0, "alpha2": -3.0, "alpha3": 28.0, "alpha_p": 88.0})
    td = env.reset()
    moves = [[-1, 0], [-1, 1], [0, 1], [1, 1]]  # per step, in steps of 2 deg (both cavities alike, then one held)
    rs, angles = [], []
    for k, move in enumerate(moves):
        acts = torch.stack([deltas_to_action(torch.tensor([move])), deltas_to_action(torch.tensor([[0, 0]]))]).flatten()
        td["action"] = acts if k % 2 == 0 else acts.flip(0)
        out = env.step(td)["next"]
        rs.append(out["r"].squeeze(-1).double())
        angles.append(env.angles_deg())
        td = TensorDict({k2: out[k2] for k2 in ("fields", "angles", "r", "round_trips", "step_count")}, batch_size=[2])
    paths = torch.stack(angles, 1)  # (2, T, 4)
    replay = follow_paths(paths, 0.1, params, StepSettings(max_round_trips=5, tol=1e-5, min_round_trips=1))
    assert torch.allclose(replay.r, torch.stack(rs, 1), rtol=1e-4, atol=1e-6)
    u, v = env.fields()
    assert torch.allclose(replay.u, u, atol=1e-4) and torch.allclose(replay.v, v, atol=1e-4)


def test_follow_paths_rejects_bad_paths():
    with pytest.raises(ValueError, match=r"\(B, T, 4\)"):
        follow_paths(torch.zeros(2, 4), 0.1, CavityParams(n=64, z_steps=2), StepSettings())
    with pytest.raises(ValueError, match="finite"):
        follow_paths(torch.full((1, 1, 4), float("nan")), 0.1, CavityParams(n=64, z_steps=2), StepSettings())
