"""The env with measured observations: its keys and specs, its reward, its noise, the stacked
history over (partial) resets, the Q-network that reads it, and its errors."""
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from laserrl.agents.dqn import build_qnet, make_actor
from laserrl.envs.factory import make_env
from laserrl.envs.laser_env import LaserCavityEnv, policy_keys
from laserrl.physics import reward_terms
from laserrl.physics.instruments import Instruments, measure, measured_reward
from laserrl.validate import ConfigError

FAST = dict(max_round_trips=4, K=0.1)
ENV = {"max_round_trips": 4, "min_round_trips": 2, "tol": None, "dtype": "complex64", "compile": False,
       "reward_center": None, "reward_scale": None, "observation": "measured", "physics": {"n": 256}}
STAGE = {"controlled": ["alpha1"], "steps_deg": [2.0], "K": 0.1, "max_steps": 4,
         "init_angles_deg": {"alpha1": [-40.0, -10.0], "alpha2": 3.0, "alpha3": 28.0, "alpha_p": 88.0}}


def test_measured_env_shows_readings_not_fields_and_rewards_their_E_over_M4():
    env = LaserCavityEnv(3, observation="measured", seed=0, **FAST)
    check_env_specs(env)
    assert policy_keys(env.task) == ("spectrum", "energy", "autocorrelation", "angles")
    td = env.rollout(3)
    assert "fields" not in td.keys() and td["spectrum"].shape == (3, 3, 64) and td["autocorrelation"].shape == (3, 3, 64)
    nxt = td["next"]
    assert torch.equal(nxt["reward"], nxt["r_measured"])
    # r is still the paper's r of the state (what evaluation reads); the reward is the readings' own
    u, v = env.fields()
    assert torch.allclose(nxt["r"][:, -1, 0], reward_terms(u, v, env.params)[2].float(), rtol=1e-5)
    assert not torch.allclose(nxt["reward"], nxt["r"])
    # the readings are measure() of the state with the env's noise: without noise they are exact
    quiet = LaserCavityEnv(3, observation="measured", seed=0, instruments=dict(
        spectrum_noise=0, spectrum_floor=0, energy_noise=0, autocorrelation_noise=0), **FAST)
    out = quiet.reset()
    m = measure(*quiet.fields(), quiet.params, quiet.task.instruments)
    assert torch.allclose(out["spectrum"], m.spectrum.float()) and torch.allclose(out["energy"][:, 0], m.energy.float())
    assert torch.allclose(out["r_measured"][:, 0], measured_reward(m).float(), rtol=1e-5)


def test_readings_are_seeded_by_the_env():
    a, b, c = (LaserCavityEnv(2, observation="measured", seed=s, **FAST) for s in (5, 5, 6))
    up = lambda td: td.set("action", torch.full((2,), 2))  # the same actions in all three
    ra, rb, rc = (env.rollout(2, policy=up) for env in (a, b, c))
    assert torch.equal(ra["next", "spectrum"], rb["next", "spectrum"])
    assert not torch.equal(ra["next", "spectrum"], rc["next", "spectrum"])


def test_history_stacks_the_last_readings_and_a_reset_fills_it_with_the_first():
    env = make_env({**ENV, "history": 3}, STAGE, 2, seed=0)
    td = env.reset()
    assert td["spectrum"].shape == (2, 3 * 64) and td["energy"].shape == (2, 3) and td["angles"].shape == (2, 12)
    assert torch.equal(td["energy"][:, 0], td["energy"][:, 2])  # padded with the first reading
    frames = [td]
    for _ in range(3):
        td = env.step(td.set("action", torch.tensor([2, 0])))["next"]
        frames.append(td)
    # oldest first: the current reading is the last, the one before it the middle
    assert torch.equal(frames[3]["energy"][:, 1], frames[2]["energy"][:, 2])
    assert torch.equal(frames[3]["angles"][:, 4:8], frames[2]["angles"][:, 8:])
    # a partial reset as collectors make it: the current data with the _reset mask
    out = env.reset(frames[3].clone().set("_reset", torch.tensor([[True], [False]])))
    assert torch.equal(out["energy"][0, 0], out["energy"][0, 2])  # the reset cavity: its first reading thrice
    assert torch.equal(out["energy"][1], frames[3]["energy"][1])  # the other keeps its history


def test_the_measured_network_reads_the_stacked_readings():
    env = make_env({**ENV, "history": 2}, STAGE, 4, seed=0)
    net = {"channels": [8], "kernel_size": 3, "pool": 2, "hidden": [32], "negative_slope": 0.01}
    qnet = build_qnet(3, {**ENV, "history": 2}, net)
    assert qnet.in_keys == ("spectrum", "energy", "autocorrelation", "angles") and qnet.history == 2
    actor = make_actor(qnet, env.action_spec_unbatched)
    td = actor(env.reset())
    assert td["action_value"].shape == (4, 3) and torch.isfinite(td["action_value"]).all()
    # without the autocorrelator the network has no such input
    qnet = build_qnet(3, {**ENV, "instruments": {"autocorrelation_points": 0, "reward": "spectrum"}}, net)
    assert qnet.in_keys == ("spectrum", "energy", "angles")


def test_the_env_carries_a_recurrent_agents_state_and_restarts_it_at_a_reset():
    env_cfg = {**ENV, "gru_size": 8}
    env = make_env(env_cfg, STAGE, 3, seed=0)
    check_env_specs(env)
    net = {"channels": [8], "kernel_size": 3, "pool": 2, "hidden": [16, 16], "negative_slope": 0.01}
    torch.manual_seed(0)
    actor = make_actor(build_qnet(3, env_cfg, net), env.action_spec_unbatched)
    td = env.reset()
    assert td["is_init"].all() and not td["recurrent_state"].any() and td["recurrent_state"].shape == (3, 1, 8)
    rollout = env.rollout(3, actor, auto_reset=False, tensordict=td)
    # each step starts from the state the step before left
    assert torch.equal(rollout["recurrent_state"][:, 1:], rollout["next", "recurrent_state"][:, :-1])
    assert rollout["recurrent_state"][:, 1:].abs().sum() > 0 and not rollout["is_init"][:, 1:].any()
    # a partial reset restarts the reset cavity's memory only
    last = rollout[:, -1]["next"].clone().set("_reset", torch.tensor([[True], [False], [False]]))
    out = env.reset(last)
    assert not out["recurrent_state"][0].any() and out["is_init"][0] and not out["is_init"][1:].any()
    assert torch.equal(out["recurrent_state"][1:], last["recurrent_state"][1:])


@pytest.mark.parametrize("change, message", [
    ({"observation": "pixels"}, r"env.observation must be one of \('fields', 'measured'\)"),
    ({"history": 0}, "env.history must be a positive integer"),
    ({"instruments": {"bins": 8}}, r"env.instruments: .*unexpected keyword argument 'bins'.*settings: \['spectrum_bins'"),
    ({"instruments": {"spectrum_noise": -1}}, "env.instruments.spectrum_noise must be >= 0"),
    ({"instruments": {"spectrum_span": 50.0}}, r"env.instruments.spectrum_span \(50\) must be <= the grid's band"),
    ({"reward_scale": 0}, "env.reward_scale must be > 0"),
])
def test_bad_measured_settings_name_the_key(change, message):
    with pytest.raises(ValueError, match=message):
        make_env({**ENV, **change}, STAGE, 2, seed=0)


def test_fields_network_refuses_a_history():
    net = {"channels": [8], "kernel_size": 3, "pool": 2, "hidden": [32], "negative_slope": 0.01}
    with pytest.raises(ConfigError, match="env.history > 1 needs env.observation=measured"):
        build_qnet(3, {**ENV, "observation": "fields", "history": 2}, net)


def test_default_instruments_fit_the_papers_grid():
    Instruments().check_grid(LaserCavityEnv(1, observation="measured", **FAST).params)
