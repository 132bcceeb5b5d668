"""env.physics_spread: every reset draws each cavity's D, E0, tau, g0, Gamma within the spread
(seeded, cavity by cavity), the step integrates each cavity with its own values, a checkpointed
env continues them, and evaluation runs the nominal cavity."""
import pytest
import torch
from omegaconf import OmegaConf

from laserrl.envs.factory import make_env
from laserrl.envs.laser_env import LaserTask
from laserrl.paths import CONF_DIR
from laserrl.physics import CavityParams
from laserrl.physics.checks import CAVITY_KEYS


def _cfgs(**env):
    base = OmegaConf.load(f"{CONF_DIR}/env/paper.yaml")
    env_cfg = OmegaConf.to_container(OmegaConf.merge(base, {"physics": {"n": 64, "z_steps": 2}, "max_round_trips": 3,
                                                            "compile": False}, env))
    return env_cfg, OmegaConf.to_container(OmegaConf.load(f"{CONF_DIR}/stage/siso.yaml"))


def test_each_reset_draws_every_cavity_within_the_spread():
    env = make_env(*_cfgs(physics_spread={"g0": 0.1, "D": 0.05}), 64, 0, centred=False)
    env.reset()
    first = env.state.cavity.clone()
    nominal = torch.tensor([getattr(CavityParams(), k) for k in CAVITY_KEYS], dtype=torch.float64)
    ratio = first / nominal
    g0, D = ratio[:, CAVITY_KEYS.index("g0")], ratio[:, CAVITY_KEYS.index("D")]
    assert float((g0 - 1).abs().max()) <= 0.1 and float((g0 - 1).abs().max()) > 0.08 and g0.std() > 0.04
    assert float((D - 1).abs().max()) <= 0.05
    assert torch.equal(ratio[:, CAVITY_KEYS.index("E0")], torch.ones(64, dtype=torch.float64))  # not spread
    env.reset()
    assert not torch.equal(env.state.cavity, first)  # drawn afresh
    again = make_env(*_cfgs(physics_spread={"g0": 0.1, "D": 0.05}), 64, 0, centred=False)
    again.reset()
    assert torch.equal(again.state.cavity, first)  # seeded


def test_the_step_runs_each_cavity_with_its_own_values():
    env = make_env(*_cfgs(physics_spread=0.1), 2, 0, centred=False)
    td = env.reset()
    env.state.u[1], env.state.v[1] = env.state.u[0], env.state.v[0]  # same fields, same angles, other cavities
    env.state.angles[1] = env.state.angles[0]
    out = env.step(td.set("action", torch.ones(2, dtype=torch.int64)))
    u = env.state.u
    assert float(torch.linalg.vector_norm(u[0] - u[1]) / torch.linalg.vector_norm(u[0])) > 1e-3
    nominal = make_env(*_cfgs(), 2, 0, centred=False)
    assert nominal.reset() is not None and nominal.state.cavity is None
    assert out["next", "r"].shape == (2, 1)


def test_a_snapshot_continues_the_cavities():
    env = make_env(*_cfgs(physics_spread=0.1), 4, 0, centred=False)
    env.reset()
    snap = env.snapshot()
    other = make_env(*_cfgs(physics_spread=0.1), 4, 1, centred=False)
    other.continue_from(snap)
    other.reset()
    assert torch.equal(other.state.cavity, env.state.cavity)


@pytest.mark.parametrize("spread, message", [(0.7, r"physics_spread.D must be a fraction in \[0, 0.5\]"),
                                             ({"Z": 0.1}, "unknown parameter"),
                                             ("lots", "physics_spread.D")])
def test_bad_spread_names_the_setting(spread, message):
    with pytest.raises(ValueError, match=message):
        LaserTask(physics_spread=spread)


def test_evaluation_runs_the_nominal_cavity():
    from laserrl.evaluate import evaluate_policy
    from laserrl.envs.actions import hold_action

    def hold(env):
        return lambda td: td.set("action", torch.full(td.batch_size, hold_action(1), dtype=torch.int64))

    env_cfg, stage = _cfgs()
    stage.update(max_steps=3)
    ev = {"steps": 2, "starts_deg": [-24.0], "success_r": 0.18, "repeats": 2}
    plain = evaluate_policy(hold, env_cfg, stage, ev)["per_start"]
    spread = evaluate_policy(hold, {**env_cfg, "physics_spread": 0.2}, stage, ev)["per_start"]
    assert [p["reward_path"] for p in plain] == [p["reward_path"] for p in spread]
