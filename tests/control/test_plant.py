"""The plant's plates: the play operator and the landing error (laserrl.control.plant.Plates),
and the real cavity plant with imperfect plates and with measured readings."""
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from laserrl.config import ConfigError
from laserrl.control.esc import observed_r
from laserrl.control.plant import CavityPlant, Plates
from laserrl.paths import CONF_DIR


def _env(**overrides):
    base = OmegaConf.load(f"{CONF_DIR}/env/paper.yaml")
    small = {"physics": {"n": 64, "z_steps": 2}, "max_round_trips": 4, "compile": False}
    return OmegaConf.to_container(OmegaConf.merge(base, small, overrides))


def _follow(plates, commands, seed=0):
    g = torch.Generator().manual_seed(seed)
    pos = prev = torch.as_tensor(commands[0], dtype=torch.float64).reshape(1, -1)
    out = []
    for c in commands[1:]:
        c = torch.as_tensor(c, dtype=torch.float64).reshape(1, -1)
        pos = plates.follow(pos, c, prev, g)
        prev = c
        out.append(pos.reshape(-1).tolist())
    return np.array(out)


def test_exact_plates_go_where_they_are_sent():
    cmds = [[0.0] * 4, [1.0, -3.0, 20.0, 89.0], [2.0, -4.0, 19.0, -89.0]]
    assert np.allclose(_follow(Plates(), cmds), cmds[1:], atol=1e-9)


def test_backlash_is_a_play_operator():
    b = 2.0
    cmds = [0.0, 0.5, 1.5, 3.0, 2.5, 1.0, 0.9, 4.0]
    pos = _follow(Plates(backlash_deg=b), [[c] * 4 for c in cmds])[:, 0]
    # a plate never lags its command by more than half the play, and moves only when pushed past it
    assert np.all(np.abs(np.array(cmds[1:]) - pos) <= b / 2 + 1e-9)
    assert pos[0] == pytest.approx(0.0)            # 0.5 deg within the play: not moved
    assert pos[2] == pytest.approx(2.0)            # pushed up: follows 1 deg behind
    assert pos[3] == pytest.approx(2.0) and pos[4] == pytest.approx(2.0)  # reversal within the play: stays
    assert pos[5] == pytest.approx(1.9)            # pushed down past the play: follows 1 deg above
    # the same command reached from the two sides lands on two different angles
    up = _follow(Plates(backlash_deg=b), [[0.0] * 4, [5.0] * 4])[-1, 0]
    down = _follow(Plates(backlash_deg=b), [[10.0] * 4, [5.0] * 4])[-1, 0]
    assert down - up == pytest.approx(b)


def test_backlash_across_the_wrap_of_the_angles():
    # 89.9 -> -89.5 deg is a turn of +0.6 deg through 90 (angles repeat every 180 deg)
    pos = _follow(Plates(backlash_deg=2.0), [[88.0] * 4, [89.9] * 4, [-89.5] * 4])[:, 0]
    assert pos[0] == pytest.approx(88.9) and pos[1] == pytest.approx(89.5)


def test_noise_lands_moved_plates_only_and_is_seeded():
    cmds = [[0.0, 0.0, 0.0, 0.0]] + [[float(t), 0.0, 0.0, 0.0] for t in range(1, 401)]
    a = _follow(Plates(noise_deg=0.5), cmds, seed=3)
    assert np.array_equal(a, _follow(Plates(noise_deg=0.5), cmds, seed=3))
    err = (a[:, 0] - np.arange(1, 401) + 90.0) % 180.0 - 90.0  # angles repeat every 180 deg
    assert 0.45 < err.std() < 0.55 and abs(err.mean()) < 0.1
    assert np.all(a[:, 1:] == 0.0)  # plates that were not moved stay put


@pytest.mark.parametrize("kwargs, name", [({"noise_deg": -0.1}, "plates.noise_deg"),
                                          ({"backlash_deg": float("inf")}, "plates.backlash_deg"),
                                          ({"backlash_deg": "1"}, "plates.backlash_deg")])
def test_bad_plates_name_the_setting(kwargs, name):
    with pytest.raises(ConfigError, match=name):
        Plates(**kwargs)


def test_the_plant_reads_back_its_commands_while_the_plates_lag():
    plant = CavityPlant(_env(), ["alpha1", "alpha2", "alpha3", "alpha_p"], 2, steps=4, seed=0,
                        plates=Plates(backlash_deg=4.0))
    start = torch.tensor([[-20.0, 3.0, 28.0, 88.0]] * 2, dtype=torch.float64)
    plant.reset(start, torch.tensor([0.1, 0.1], dtype=torch.float64))
    cmd = start + torch.tensor([[1.0, 0.0, 0.0, 0.0], [3.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    obs = plant.step(cmd)
    assert torch.allclose(plant.angles_deg, cmd)  # what the controllers know
    assert torch.allclose(obs["angles"].double(), torch.deg2rad(cmd), atol=1e-6)
    true = plant.true_angles_deg
    assert true[0, 0] == pytest.approx(-20.0, abs=1e-9)  # within the play: the plate did not move
    assert true[1, 0] == pytest.approx(-19.0, abs=1e-9)  # pushed 1 deg past the play


def test_controllers_read_the_instruments_reward_when_measured():
    env = _env(observation="measured", instruments={"spectrum_bins": 16, "spectrum_span": 6.0, "autocorrelation_points": 16})
    plant = CavityPlant(env, ["alpha1"], 2, steps=3, seed=0)
    start = torch.tensor([[-20.0, 3.0, 28.0, 88.0]] * 2, dtype=torch.float64)
    obs = plant.reset(start, torch.tensor([0.1, 0.1], dtype=torch.float64))
    obs = plant.step(start)
    assert np.allclose(observed_r(obs), obs["r_measured"].reshape(-1).numpy())
    assert not np.allclose(observed_r(obs), plant.r.numpy())  # its own scale, not the paper's r


def test_a_plant_with_stacked_readings_starts_where_it_is_told():
    env = _env(observation="measured", history=3, instruments={"spectrum_bins": 16, "spectrum_span": 6.0,
                                                               "autocorrelation_points": 16})
    plant = CavityPlant(env, ["alpha1", "alpha2", "alpha3", "alpha_p"], 2, steps=3, seed=0, plates=Plates(backlash_deg=2.0))
    start = torch.tensor([[60.0, 3.0, 28.0, 88.0], [-70.0, 3.0, 28.0, 88.0]], dtype=torch.float64)
    obs = plant.reset(start, torch.tensor([-0.15, 0.3], dtype=torch.float64))
    assert torch.allclose(plant.true_angles_deg, start) and torch.allclose(plant.env.state.K, torch.tensor([-0.15, 0.3], dtype=torch.float64))
    assert obs["angles"].shape == (2, 12)  # three readings of four angles, each the start
    assert torch.allclose(obs["angles"].double(), torch.deg2rad(start).repeat(1, 3), atol=1e-6)
    cmd = start + torch.tensor([[0.5, 0, 0, 0], [3.0, 0, 0, 0]], dtype=torch.float64)
    obs = plant.step(cmd)
    assert torch.allclose(obs["angles"][:, -4:].double(), torch.deg2rad(cmd), atol=1e-6)  # the newest: the commands
    assert plant.true_angles_deg[0, 0] == pytest.approx(60.0) and plant.true_angles_deg[1, 0] == pytest.approx(-68.0)


def test_a_physics_spread_gives_every_controller_the_same_other_cavities():
    """physics_spread: num_cavities // copies cavities drawn within +-spread of the nominal one and
    repeated per copy, and the cavity runs with them (r differs from the nominal cavity's)."""
    from laserrl.envs.laser_env import base_env_of
    from laserrl.physics.checks import CAVITY_KEYS

    angles = torch.tensor([[-20.0, 3.0, 28.0, 88.0]] * 4, dtype=torch.float64)
    K = torch.full((4,), 0.1, dtype=torch.float64)
    runs = {}
    for spread in (None, 0.1):
        plant = CavityPlant(_env(), ["alpha1"], 4, steps=2, seed=0, physics_spread=spread, copies=2)
        plant.reset(angles, K)
        runs[spread] = (plant, plant.step(angles)["r"].squeeze(-1))
    plant, r = runs[0.1]
    assert runs[None][0].cavities is None
    nominal = base_env_of(plant.env).params
    nominal = torch.tensor([float(getattr(nominal, k)) for k in CAVITY_KEYS], dtype=torch.float64)
    cav = plant.cavities
    assert torch.equal(cav[:2], cav[2:]) and not torch.equal(cav[0], cav[1])
    assert ((cav / nominal - 1).abs() <= 0.1 + 1e-12).all() and ((cav / nominal - 1).abs() > 0.01).any()
    assert torch.equal(base_env_of(plant.env).state.cavity, cav)
    assert torch.allclose(r[:2], r[2:]) and not torch.allclose(r, runs[None][1])
    with pytest.raises(ValueError, match="physics_spread"):
        CavityPlant(_env(), ["alpha1"], 4, steps=2, physics_spread=0.9)
    with pytest.raises(ValueError, match="copies"):
        CavityPlant(_env(), ["alpha1"], 5, steps=2, physics_spread=0.1, copies=2)
