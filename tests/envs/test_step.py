"""The pure agent step: the cavity answers new angles within the step, the paper's rule
shows the old angle after a turn of alpha1 alone, and the env steps with exactly this function."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from laserrl.envs import LaserCavityEnv, hold_action
from laserrl.envs.step import CavityState, StepNumerics, apply_action, observe, step, step_cavity
from laserrl.physics import CavityParams, reward_terms, sech_fields

PARAMS = CavityParams(n=128, z_steps=4)
ANGLES = torch.deg2rad(torch.tensor([[-24.0, 3.0, 28.0, 88.0]], dtype=torch.float64))


@pytest.fixture(scope="module")
def settled() -> CavityState:
    """The mode-locked pulse at alpha1 = -24 deg, K = 0.1, run to convergence."""
    u, v = sech_fields(1, PARAMS)
    state = CavityState(u=u, v=v, angles=ANGLES.clone(), K=torch.tensor([0.1], dtype=torch.float64),
                        step_count=torch.zeros(1, dtype=torch.int64), batch_size=[1])
    state, out = step_cavity(state, ANGLES, PARAMS, StepNumerics(max_round_trips=500, min_round_trips=1))
    assert bool(out.converged.all()) and float(out.r) > 0.18
    return state


def turned_alpha1(deg: float) -> torch.Tensor:
    turned = ANGLES.clone()
    turned[0, 0] += math.radians(deg)
    return turned


def test_turning_alpha1_alone_changes_r_within_the_step(settled):
    r0 = reward_terms(settled.u, settled.v, PARAMS)[2]
    after, out = step_cavity(settled, turned_alpha1(4.0), PARAMS, StepNumerics())  # the default: >= 2 round trips
    assert int(out.round_trips) >= 2
    assert not torch.allclose(out.r, r0, rtol=1e-3)
    assert int(after.step_count) == int(settled.step_count) + 1


def test_the_papers_rule_stops_after_one_round_trip_on_the_old_intensity(settled):
    """J1 is unitary and last: with min_round_trips = 1 a settled cavity passes the stopping
    test after one round trip and the step shows the angle before the turn."""
    r0 = reward_terms(settled.u, settled.v, PARAMS)[2]
    _, out = step_cavity(settled, turned_alpha1(4.0), PARAMS, StepNumerics(min_round_trips=1))
    assert int(out.round_trips) == 1
    assert torch.allclose(out.r, r0, rtol=1e-4)


def test_the_env_steps_with_the_pure_step():
    env = LaserCavityEnv(3, controlled=("alpha1", "alpha2"), steps_deg=(2.0, 3.0), max_round_trips=4, seed=0)
    td = env.reset()
    before = env.state.clone()
    action = torch.tensor([0, 4, 8])
    out = env.step(td.set("action", action))["next"]
    expected, measured = step(before, action, torch.deg2rad(torch.tensor([2.0, 3.0], dtype=torch.float64)),
                              torch.tensor([0, 1]), env.params, env.task.numerics)
    assert torch.equal(out["r"].squeeze(-1), measured.r.to(torch.float32))
    assert torch.equal(out["round_trips"].squeeze(-1), measured.round_trips)
    assert torch.equal(out["fields"], observe(expected)["fields"])
    assert torch.equal(env.state.angles, expected.angles)


def test_apply_action_turns_only_the_controlled_plates():
    angles = torch.zeros(2, 4, dtype=torch.float64)
    steps = torch.tensor([0.1, 0.2], dtype=torch.float64)
    out = apply_action(angles, torch.tensor([hold_action(2), 0]), steps, torch.tensor([1, 3]))
    assert torch.equal(out[0], angles[0])
    assert torch.allclose(out[1], torch.tensor([0.0, -0.1, 0.0, -0.2], dtype=torch.float64))


@pytest.mark.parametrize("kwargs, pattern", [
    (dict(min_round_trips=0), "min_round_trips must be a positive integer"),
    (dict(max_round_trips=2.5), "max_round_trips must be a positive integer"),
    (dict(max_round_trips=1, min_round_trips=2), r"min_round_trips \(2\) must be <= max_round_trips \(1\)"),
    (dict(tol=-1.0), "tol must be a number >= 0"),
])
def test_bad_numerics_name_the_field(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        StepNumerics(**kwargs)


def test_env_task_rejects_min_above_max():
    with pytest.raises(ValueError, match="min_round_trips"):
        LaserCavityEnv(1, max_round_trips=1, min_round_trips=2)


def test_partial_reset_keeps_the_other_cavities_state():
    env = LaserCavityEnv(2, max_round_trips=2, seed=1)
    td = env.reset()
    env.step(td.set("action", torch.tensor([2, 2])))
    kept = env.state[1].clone()
    env.reset(TensorDict(_reset=torch.tensor([True, False]), batch_size=[2]))
    assert int(env.state.step_count[0]) == 0 and int(env.state.step_count[1]) == 1
    assert torch.equal(env.state.u[1], kept.u) and torch.equal(env.state.angles[1], kept.angles)


def test_a_saved_env_config_without_the_key_keeps_the_papers_rule():
    """Runs saved before env.min_round_trips existed stepped with the paper's rule."""
    from omegaconf import OmegaConf

    from laserrl.envs.factory import make_task
    from laserrl.paths import CONF_DIR

    env_cfg = OmegaConf.to_container(OmegaConf.load(f"{CONF_DIR}/env/paper.yaml"))
    stage_cfg = OmegaConf.to_container(OmegaConf.load(f"{CONF_DIR}/stage/siso.yaml"))
    assert make_task(env_cfg, stage_cfg).min_round_trips == 2
    del env_cfg["min_round_trips"]
    assert make_task(env_cfg, stage_cfg).min_round_trips == 1
