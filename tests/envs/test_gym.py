"""The Gymnasium entry points (laserrl.gym): registration, API conformance, seeding, the
training reward, the batched vector env and its autoreset, and errors for bad keywords."""
from __future__ import annotations

import math
import subprocess
import sys

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode, VectorEnv

import laserrl  # noqa: F401  registers the ids
from laserrl.envs.factory import make_env
from laserrl.gym import ENV_IDS, ModeLockVectorEnv, load_configs
from laserrl.validate import ConfigError

SISO = "laserrl/ModeLock-SISO-v0"
# a coarse grid, few integrator steps and one round trip per agent step keep a step ~10 ms
FAST = dict(physics={"n": 64, "z_steps": 2}, max_round_trips=1, min_round_trips=1, threads=1)
# check_env warns that the fields' Box is unbounded: it is (the fields have no fixed bound)
unbounded_fields = pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum) value")


def test_every_id_is_registered_on_import_laserrl():
    ids = {f"laserrl/ModeLock-{task}{variant}-v0"
           for task in ("SISO", "Duo", "MISO") for variant in ("", "-PaperExact")}
    assert set(ENV_IDS) == ids
    for env_id in ids:
        spec = gymnasium.spec(env_id)
        assert spec.entry_point == "laserrl.gym:ModeLockEnv"
        assert spec.vector_entry_point == "laserrl.gym:ModeLockVectorEnv"


def test_import_laserrl_registers_without_loading_torchrl():
    code = ("import sys, gymnasium, laserrl; print('laserrl/ModeLock-MISO-v0' in gymnasium.registry, "
            "'torchrl' in sys.modules, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300)
    assert out.stdout.split() == ["True", "False", "False"]  # torch and TorchRL load when an env is made


@unbounded_fields
def test_check_env_default_id():
    env = gymnasium.make(SISO, threads=1)
    check_env(env.unwrapped)
    task = env.unwrapped.torchrl_env.base_env.task
    # the Hydra defaults (env=paper stage=siso), except compile
    assert (task.max_round_trips, task.min_round_trips, task.dtype, task.compile) == (30, 2, "complex64", False)
    assert task.controlled == ("alpha1",) and task.max_steps == 20


@unbounded_fields
@pytest.mark.parametrize("env_id", ["laserrl/ModeLock-Duo-v0", "laserrl/ModeLock-MISO-PaperExact-v0"])
def test_check_env_other_ids_small(env_id):
    check_env(gymnasium.make(env_id, **FAST).unwrapped)


@pytest.mark.parametrize("env_id", sorted(ENV_IDS))
def test_spaces_and_a_few_steps(env_id):
    stage, _ = ENV_IDS[env_id]
    m = {"siso": 1, "duo": 2, "miso": 4}[stage]
    env = gymnasium.make(env_id, **FAST)
    assert env.action_space == gymnasium.spaces.Discrete(3**m)
    assert env.observation_space["fields"].shape == (4, 64) and env.observation_space["angles"].shape == (4,)
    obs, info = env.reset(seed=0)
    assert obs in env.observation_space and obs["fields"].dtype == np.float32
    env.action_space.seed(0)
    for _ in range(3):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert obs in env.observation_space
        assert isinstance(reward, float) and math.isfinite(reward)
        assert terminated is False and truncated is False
        assert info["round_trips"] == 1 and 0 < info["r"] < 1


def test_paper_exact_ids_have_the_paper_exact_numerics():
    env_cfg, stage_cfg = load_configs("miso", "paper_exact")
    task = gymnasium.make("laserrl/ModeLock-MISO-PaperExact-v0").unwrapped.torchrl_env.base_env.task
    assert (task.min_round_trips, task.max_round_trips, task.dtype, task.tol) == (1, 500, "complex128", 1e-6)
    assert task.max_round_trips == env_cfg["max_round_trips"] and task.max_steps == stage_cfg["max_steps"] == 100
    assert task.controlled == ("alpha1", "alpha2", "alpha3", "alpha_p") and task.init_fields == "noise"
    assert gymnasium.make(SISO).unwrapped.torchrl_env.base_env.task.dtype == "complex64"


def test_reset_seed_reproduces_and_seeds_differ():
    env = gymnasium.make(SISO, **FAST)
    first, _ = env.reset(seed=3)
    again, _ = env.reset(seed=3)
    other, _ = env.reset(seed=4)
    assert np.array_equal(first["angles"], again["angles"]) and np.array_equal(first["fields"], again["fields"])
    assert first["angles"][0] != other["angles"][0]  # alpha1 is drawn from [-40, -10] deg
    assert -40 <= math.degrees(first["angles"][0]) <= -10
    # unseeded resets go on from the seeded generator, reproducibly
    env.reset(seed=3)
    follow, _ = env.reset()
    env.reset(seed=3)
    assert np.array_equal(env.reset()[0]["angles"], follow["angles"])


def test_reward_is_the_training_envs_and_info_has_raw_r():
    """Same seed, same actions: the gym env gives the rewards of laserrl-train's env."""
    env_cfg, stage_cfg = load_configs("siso")
    env_cfg.update(compile=False, max_round_trips=1, min_round_trips=1)
    env_cfg["physics"].update(n=64, z_steps=2)
    training = make_env(env_cfg, stage_cfg, 1, seed=5)
    td = training.reset()
    env = gymnasium.make(SISO, **FAST)
    obs, _ = env.reset(seed=5)
    np.testing.assert_array_equal(obs["angles"], td["angles"][0].numpy())
    for action in (2, 2, 0):
        td["action"] = torch.tensor([action])
        out = training.step(td)["next"]
        obs, reward, _, _, info = env.step(action)
        assert reward == pytest.approx(float(out["reward"]), abs=1e-6)
        assert info["r"] == pytest.approx(float(out["r"]), abs=1e-7)
        # the paper's centring of env=paper: (r - 0.1) / 0.1
        assert reward == pytest.approx((info["r"] - 0.1) / 0.1, abs=1e-5)
        td = out
    raw = gymnasium.make(SISO, **FAST, reward_center=0.0, reward_scale=1.0)
    raw.reset(seed=5)
    _, reward, _, _, info = raw.step(2)
    assert reward == pytest.approx(info["r"], abs=1e-7)


def test_actions_turn_the_controlled_angles():
    env = gymnasium.make(SISO, **FAST)
    obs, _ = env.reset(seed=0, options={"angles_deg": [-30.0, 3.0, 28.0, 88.0]})
    np.testing.assert_allclose(np.degrees(obs["angles"]), [-30.0, 3.0, 28.0, 88.0], atol=1e-5)
    for action, alpha1 in ((2, -28.0), (2, -26.0), (1, -26.0), (0, -28.0)):  # increase, increase, hold, decrease
        obs, *_ = env.step(action)
        np.testing.assert_allclose(np.degrees(obs["angles"]), [alpha1, 3.0, 28.0, 88.0], atol=1e-5)
    duo = gymnasium.make("laserrl/ModeLock-Duo-v0", **FAST)
    obs, _ = duo.reset(seed=0)
    start = np.degrees(obs["angles"])
    obs, *_ = duo.step(2 * 3 + 1)  # digit 1 (alpha2) up, digit 0 (alpha1) hold
    np.testing.assert_allclose(np.degrees(obs["angles"]) - start, [0.0, 2.0, 0.0, 0.0], atol=1e-5)


def test_truncated_after_the_tasks_max_steps():
    env = gymnasium.make(SISO, **FAST, max_steps=3)
    env.reset(seed=0)
    assert [env.step(1)[3] for _ in range(3)] == [False, False, True]


def test_reset_options_set_K():
    env = gymnasium.make(SISO, **FAST)
    env.reset(seed=0, options={"K": 0.25})
    assert env.unwrapped.torchrl_env.base_env.K.tolist() == [0.25]
    with pytest.raises(ValueError, match="unknown key"):
        env.reset(options={"alpha1": 3})


# ----------------------------------------------------------------------------- vector env
def make_vec(num_envs=3, **kwargs):
    return gymnasium.make_vec(SISO, num_envs=num_envs, vectorization_mode="vector_entry_point", **FAST, **kwargs)


def test_make_vec_is_one_batched_env():
    env = make_vec(4)
    assert isinstance(env, ModeLockVectorEnv) and isinstance(env, VectorEnv) and env.num_envs == 4
    assert env.unwrapped.torchrl_env.batch_size == torch.Size([4])  # one env of 4 cavities, not 4 envs
    assert env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert env.single_action_space == gymnasium.spaces.Discrete(3)
    obs, info = env.reset(seed=0)
    assert obs["fields"].shape == (4, 4, 64) and obs["angles"].shape == (4, 4)
    assert obs in env.observation_space and info["r"].shape == (4,) and info["_r"].all()
    assert len(set(obs["angles"][:, 0].tolist())) == 4  # each cavity draws its own start
    obs, reward, terminated, truncated, info = env.step(np.array([0, 1, 2, 2]))
    assert reward.shape == terminated.shape == truncated.shape == (4,) and not terminated.any()
    np.testing.assert_allclose(reward, (info["r"] - 0.1) / 0.1, atol=1e-5)
    again, _ = env.reset(seed=0)
    assert np.array_equal(again["angles"], env.reset(seed=0)[0]["angles"])


def test_vector_autoreset_next_step():
    env = make_vec(3, max_steps=2)
    env.reset(seed=0)
    env.step(np.array([2, 2, 2]))
    last, _, _, truncated, _ = env.step(np.array([2, 2, 2]))
    assert truncated.all()
    first, reward, terminated, truncated, info = env.step(np.array([2, 2, 2]))  # resets, ignores the actions
    assert not truncated.any() and not terminated.any() and (reward == 0).all() and (info["round_trips"] == 0).all()
    assert not np.array_equal(first["angles"][:, 0], last["angles"][:, 0])
    assert all(-40 <= a <= -10 for a in np.degrees(first["angles"][:, 0]))
    # and the new episodes run: one step later the physics steps again
    assert (env.step(np.array([1, 1, 1]))[4]["round_trips"] == 1).all()


def test_vector_autoreset_next_step_after_a_partial_reset():
    env = make_vec(3, max_steps=2)
    env.reset(seed=0)
    env.step(np.array([1, 1, 1]))
    env.reset(options={"reset_mask": np.array([True, False, False])})  # cavity 0 starts over
    _, _, _, truncated, _ = env.step(np.array([1, 1, 1]))
    assert truncated.tolist() == [False, True, True]
    _, reward, _, truncated, info = env.step(np.array([2, 2, 2]))
    assert truncated.tolist() == [True, False, False]  # cavity 0 ends, 1 and 2 restart
    assert reward[0] != 0 and reward[1] == reward[2] == 0
    assert info["round_trips"].tolist() == [1, 0, 0]


def test_vector_autoreset_same_step():
    env = make_vec(2, max_steps=2, autoreset_mode="SameStep")
    assert env.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    env.reset(seed=0)
    stepped, *_ = env.step(np.array([2, 0]))
    obs, reward, _, truncated, info = env.step(np.array([2, 0]))
    assert truncated.all() and (reward != 0).all() and info["_final_obs"].all()
    # the step's last state is in final_obs, the next episode's first in obs
    np.testing.assert_allclose(np.degrees(info["final_obs"][0]["angles"][0] - stepped["angles"][0, 0]), 2.0, atol=1e-5)
    np.testing.assert_allclose(np.degrees(info["final_obs"][1]["angles"][0] - stepped["angles"][1, 0]), -2.0, atol=1e-5)
    assert (info["round_trips"] == 0).all() and (info["final_info"]["round_trips"] == 1).all()
    assert not np.array_equal(obs["angles"][:, 0], stepped["angles"][:, 0])
    assert not env.step(np.array([1, 1]))[3].any()


def test_vector_autoreset_disabled_needs_a_reset():
    env = make_vec(2, max_steps=1, autoreset_mode="Disabled")
    env.reset(seed=0)
    assert env.step(np.array([1, 1]))[3].all()
    with pytest.raises(RuntimeError, match="reset_mask"):
        env.step(np.array([1, 1]))
    env.reset(options={"reset_mask": np.array([True, True])})
    assert env.step(np.array([1, 1]))[3].all()


# ----------------------------------------------------------------------------- errors
@pytest.mark.filterwarnings("ignore:.*render_mode")  # gymnasium warns before the env refuses it
@pytest.mark.parametrize("kwargs, message", [
    (dict(max_round_trip=5), r"unknown keyword argument\(s\) \['max_round_trip'\]"),
    (dict(K="big"), r"^K must be a number or a \[low, high\] pair"),
    (dict(max_round_trips=0), r"^max_round_trips must be a positive integer"),
    (dict(dtype="float32"), r"^dtype must be one of"),
    (dict(compile="yes"), r"^compile must be True or False"),
    (dict(physics={"n": 3}), r"^physics\.n "),
    (dict(physics={"gain": 1.0}), r"^physics: unknown key\(s\) \['gain'\]"),
    (dict(init_angles_deg={"alpha9": 1.0}), r"^init_angles_deg: unknown angle"),
    (dict(threads=0), r"^threads must be"),
    (dict(device="tpu"), r"^device"),
    (dict(render_mode="rgb_array"), r"^render_mode"),
    (dict(stage="quad"), r"^stage must be one of duo, miso, siso"),
])
def test_bad_keywords_raise_one_config_error(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        gymnasium.make(SISO, **kwargs)


def test_bad_vector_keywords():
    with pytest.raises(ConfigError, match="^num_envs must be a positive integer"):
        gymnasium.make_vec(SISO, num_envs=0, vectorization_mode="vector_entry_point")
    with pytest.raises(ConfigError, match="^autoreset_mode must be one of"):
        make_vec(2, autoreset_mode="sometimes")
    with pytest.raises(ValueError, match="one int"):
        make_vec(2).reset(seed=[1, 2])


def test_keywords_override_the_config():
    env = gymnasium.make(SISO, K=[0.0, 0.2], init_angles_deg={"alpha1": -20.0}, dtype="complex128",
                         max_round_trips=7)
    task = env.unwrapped.torchrl_env.base_env.task
    assert task.K == (0.0, 0.2) and task.max_round_trips == 7 and task.dtype == "complex128"
    # a partial init_angles_deg keeps the stage's other angles
    assert task.init_angles_deg == {"alpha1": (-20.0, -20.0), "alpha2": (3.0, 3.0), "alpha3": (28.0, 28.0),
                                    "alpha_p": (88.0, 88.0)}


@unbounded_fields  # the readings' Boxes are unbounded too
def test_measured_observation_passes_the_checker():
    measured = dict(FAST, observation="measured", instruments={"spectrum_span": 6.0, "autocorrelation_points": 16})
    env = gymnasium.make(SISO, **measured)
    check_env(env.unwrapped)
    obs, info = env.reset(seed=0)
    assert set(obs) == {"spectrum", "energy", "autocorrelation", "angles"} and obs["spectrum"].shape == (64,)
    assert obs["autocorrelation"].shape == (16,) and "r" in info
    with pytest.raises(ConfigError, match="history: the Gymnasium envs give one observation per step"):
        gymnasium.make(SISO, history=2, **measured)
    with pytest.raises(ConfigError, match="gru_size: the Gymnasium envs give observations only"):
        gymnasium.make(SISO, gru_size=8, **measured)
