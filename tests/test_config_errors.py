"""Hostile config values (issue: reliability): each gives one clear error naming its config
key before anything is built, never a crash deep inside torch; random env configs either
build a working env or fail with such an error; no NaN reaches the replay buffer."""
import math
import re
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import MissingConfigException
from hypothesis import HealthCheck, given, settings, strategies as st
from omegaconf import OmegaConf
from torchrl.envs.utils import check_env_specs

from laserrl.agents.dqn import make_replay
from laserrl.config import ConfigError
from laserrl.train import check_train_config
from laserrl.envs.factory import make_env
from laserrl.envs.laser_env import ANGLE_NAMES
from laserrl.physics import NonFiniteFieldError
from laserrl.paths import CONF_DIR

CONF = Path(CONF_DIR)


def _compose(overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=["run_dir=/tmp/x", *overrides])


@pytest.mark.parametrize("override, key", [
    # zero or negative sizes and counts
    ("env.num_envs=0", "env.num_envs"), ("env.num_envs=-8", "env.num_envs"),
    ("collector.frames_per_batch=0", "collector.frames_per_batch"),
    ("collector.frames_per_batch=-128", "collector.frames_per_batch"),
    ("collector.frames_per_batch=100", "collector.frames_per_batch"),  # not a multiple of env.num_envs
    ("train.total_frames=0", "train.total_frames"), ("train.total_frames=-40960", "train.total_frames"),
    ("train.checkpoint_every_frames=0", "train.checkpoint_every_frames"),
    ("train.eval_every_frames=-1", "train.eval_every_frames"), ("train.max_minutes=0", "train.max_minutes"),
    ("train.stop_at_success=1.5", "train.stop_at_success"),
    ("optim.batch_size=0", "optim.batch_size"), ("replay.size=-1", "replay.size"),
    ("env.max_round_trips=0", "env.max_round_trips"), ("collector.num_workers=0", "collector.num_workers"),
    # negative steps: episode length, evaluation steps, step sizes
    ("stage.max_steps=-20", "stage.max_steps"), ("stage.max_steps=0", "stage.max_steps"),
    ("stage.move_cost=-0.01", "stage.move_cost"), ("stage.move_cost=inf", "stage.move_cost"),
    ("stage.move_cost_from=nan", "stage.move_cost_from"),
    ("eval.steps=-1", "eval.steps"), ("eval.repeats=0", "eval.repeats"),
    ("stage.steps_deg=[0.0]", "stage.steps_deg"), ("stage.steps_deg=[-2.0]", "stage.steps_deg"),
    ("stage.steps_deg=[2.0,2.0]", "stage.steps_deg"),  # one per controlled angle
    # names
    ("stage.controlled=[alpha9]", "stage.controlled"), ("stage.controlled=[alpha1,alpha1]", "stage.controlled"),
    ("stage.init_fields=gaussian", "stage.init_fields"), ("env.dtype=float16", "env.dtype"),
    ("replay.kind=fifo", "replay.kind"), ("agent.loss_function=huber", "agent.loss_function"),
    ("agent.exploration.kind=cosine", "agent.exploration.kind"), ("device=tpu", "device"),
    # ranges with low > high, non-finite values
    ("stage.init_angles_deg.alpha1=[-10,-40]", "stage.init_angles_deg.alpha1"),
    ("stage.K=[0.4,0.1]", "stage.K"), ("stage.K=nan", "stage.K"), ("stage.K=inf", "stage.K"),
    ("stage.K=[0,-inf]", "stage.K"), ("stage.init_angles_deg.alpha_p=nan", "stage.init_angles_deg.alpha_p"),
    ("eval.K=[0.1,nan]", "eval.K"), ("eval.success_r=inf", "eval.success_r"), ("eval.init_fields=gauss", "eval.init_fields"),
    ("optim.lr=nan", "optim.lr"), ("optim.lr=-1e-3", "optim.lr"), ("agent.gamma=1.5", "agent.gamma"),
    ("agent.n_steps=0", "agent.n_steps"), ("agent.n_steps=2.5", "agent.n_steps"), ("agent.n_steps=null", "agent.n_steps"),
    ("optim.lr_decay=0", "optim.lr_decay"), ("optim.lr_decay=1.5", "optim.lr_decay"), ("optim.lr_decay=fast", "optim.lr_decay"),
    ("optim.lr_decay_updates=0", "optim.lr_decay_updates"), ("optim.lr_decay_updates=2.5", "optim.lr_decay_updates"),
    ("agent.exploration.end=1.5", "agent.exploration.end"),  # end <= start <= 1
    ("agent.exploration.decay_frames=0", "agent.exploration.decay_frames"),
    ("agent.target.tau=0", "agent.target.tau"), ("env.tol=-1e-5", "env.tol"),
    ("env.reward_scale=0", "env.reward_scale"), ("env.reward_center=inf", "env.reward_center"),
    ("+stage.sech_amplitude=1e9", "stage.sech_amplitude"), ("+stage.noise_scale=-0.1", "stage.noise_scale"),
    # physics and network
    ("env.physics.n=100", "env.physics.n"), ("env.physics.z_steps=0", "env.physics.z_steps"),
    ("env.physics.T=-60", "env.physics.T"), ("env.physics.Gamma=nan", "env.physics.Gamma"),
    ("agent.network.channels=[16,0]", "agent.network.channels"), ("agent.network.kernel_size=4", "agent.network"),
    ("agent.network.pool=64", "agent.network"), ("agent.network.head=joined", "agent.network.head"),
    ("seed=-1", "seed"), ("threads=0", "threads"),
    # wrong types
    ("env.num_envs=many", "env.num_envs"), ("stage.K=[0.1,high]", "stage.K"), ("stage.steps_deg=2", "stage.steps_deg"),
    ("stage.max_steps=2.5", "stage.max_steps"),
    # integers that are not finite
    ("train.total_frames=inf", "train.total_frames"), ("collector.frames_per_batch=nan", "collector.frames_per_batch"),
    ("env.num_envs=inf", "env.num_envs"),
    # a recurrent agent's memory
    ("env.gru_size=0", "env.gru_size"), ("env.gru_size=2.5", "env.gru_size"), ("env.gru_size=true", "env.gru_size"),
    ("env.gru_size=32", "env.gru_size"),  # with the fields observation
    # a second validation of the best weights
    ("train.reselect={top:3,repeats:2}", "train.reselect"),  # without train.keep_best
    ("train.reselect={top:1,repeats:2}", "train.reselect.top"), ("train.reselect={top:3}", "train.reselect"),
    ("train.reselect={top:3,repeats:0}", "train.reselect.repeats"),
    ("train.reselect={top:3,repeats:2,K:[0.1,nan]}", "train.reselect.K"),
    ("train.reselect={top:3,repeats:2,seed:4}", "train.reselect"),
])
def test_hostile_value_names_its_key(override, key):
    cfg = _compose([override])
    with pytest.raises(ValueError) as info:  # ConfigError is a ValueError, as are the builders' errors
        check_train_config(cfg)
    message = str(info.value)
    assert message.startswith(key) or message.startswith(f"{key}[") or f"{key} " in message or f"{key}:" in message, message
    assert "\n" not in message


@pytest.mark.parametrize("collector", [["collector=multi_sync", "collector.kind=multi_async"], ["collector=ray", "collector.sync=false"]])
def test_n_step_returns_refuse_collectors_that_interleave_envs(collector):
    # n-step returns join a batch to the one before, so every batch must come from the same envs
    cfg = _compose(["agent.n_steps=3", *collector])
    with pytest.raises(ValueError, match=r"^agent.n_steps=3 needs batches from every env in turn"):
        check_train_config(cfg)
    check_train_config(_compose(["agent.n_steps=3", "collector=multi_sync"]))


@pytest.mark.parametrize("override, match", [
    (["collector.frames_per_batch=64"], "sequences of collector.frames_per_batch / env.num_envs steps, here 1"),
    (["agent.n_steps=3"], "one-step targets"), (["collector=multi_sync"], "collector=sync, not multi_sync"),
    (["optim.batch_size=8"], "optim.batch_size \\(8\\) must hold at least one sequence of 16 steps"),
])
def test_recurrent_agent_rules_across_groups(override, match):
    # a GRU learns from each cavity's steps of one batch, stored together
    recurrent = ["env.observation=measured", "env.gru_size=16", "env.num_envs=64", "collector.frames_per_batch=1024"]
    check_train_config(_compose(recurrent))
    with pytest.raises(ValueError, match=match):
        check_train_config(_compose([*recurrent, *override]))


@pytest.mark.parametrize("override, group", [("stage=nosuch", "stage"), ("env=nosuch", "env")])
def test_unknown_config_choice_names_the_group(override, group):
    with pytest.raises(MissingConfigException, match=rf"'{group}/nosuch'"):
        _compose([override])


def test_unknown_curriculum_stage_fails_before_any_training(tmp_path):
    from laserrl.experiments import run_curriculum

    cfg = _compose(["experiment=curriculum", f"run_dir={tmp_path}", "curriculum.stages=[siso,nosuch,miso]"])
    with pytest.raises(ConfigError, match=r"curriculum.stages: unknown stage 'nosuch'"):
        run_curriculum(cfg)
    assert not any(tmp_path.iterdir())


def test_bad_value_in_a_later_curriculum_stage_fails_before_any_training(tmp_path):
    from laserrl.experiments import run_curriculum

    cfg = _compose(["experiment=curriculum", f"run_dir={tmp_path}",
                    "++curriculum.config_overrides.miso.eval.held_steps=500"])
    with pytest.raises(ConfigError, match=r"curriculum stage 'miso': eval.held_steps"):
        run_curriculum(cfg)
    assert not any(tmp_path.iterdir())


def test_the_default_configs_pass():
    check_train_config(_compose([]))
    check_train_config(_compose(["experiment=smoke"]))


# ----------------------------------------------------------------------------- fuzz: random env configs
KEY = re.compile(r"^(env\.num_envs|env\.max_round_trips|env\.min_round_trips|env\.tol|env\.dtype|env\.reward_\w+|env\.physics\.\w+|"
                 r"stage\.(controlled|steps_deg|init_angles_deg(\.\w+)?|K|init_fields|sech_\w+|noise_scale|max_steps))\b")
FINITE = st.floats(-100, 100, allow_nan=False)
HOSTILE_NUMBER = st.sampled_from([0.0, -1.0, math.nan, math.inf, -math.inf, 1e12, "x", None, [1.0]])
HOSTILE_RANGE = st.one_of(HOSTILE_NUMBER, st.tuples(FINITE, FINITE).filter(lambda r: r[0] > r[1]).map(list),
                          st.lists(FINITE, min_size=3, max_size=3), st.just([0.0, math.nan]))


HOSTILE_ONE_IN_12 = st.sampled_from([False] * 11 + [True])


def valid_range(lo=-100.0, hi=100.0):
    return st.one_of(st.floats(lo, hi), st.tuples(st.floats(lo, hi), st.floats(lo, hi)).map(sorted))


@st.composite
def env_configs(draw):
    """Env and stage configs where each value is hostile with probability 1/12 (about a third
    of the configs are entirely valid)."""
    def pick(valid, hostile):
        return draw(hostile) if draw(HOSTILE_ONE_IN_12) else draw(valid)

    names = pick(st.lists(st.sampled_from(ANGLE_NAMES), min_size=1, max_size=4, unique=True),
                 st.sampled_from([[], ["alpha9"], ["alpha1", "alpha1"], "alpha1", [1]]))
    m = len(names) if isinstance(names, list) else 1
    init = {a: pick(valid_range(-180, 180), HOSTILE_RANGE) for a in ANGLE_NAMES}
    if draw(HOSTILE_ONE_IN_12):
        init.pop(draw(st.sampled_from(ANGLE_NAMES)))
    stage = {
        "controlled": names,
        "steps_deg": pick(st.lists(st.floats(0.1, 45), min_size=m, max_size=m),
                          st.one_of(st.lists(HOSTILE_NUMBER, min_size=m, max_size=m), st.just([2.0] * (m + 1)), st.just(2.0))),
        "init_angles_deg": init,
        "K": pick(valid_range(-2, 2), HOSTILE_RANGE),
        "init_fields": pick(st.sampled_from(["sech", "noise"]), st.sampled_from(["flat", None])),
        "sech_amplitude": pick(st.floats(0.01, 10), HOSTILE_NUMBER),
        "noise_scale": pick(st.floats(1e-3, 10), HOSTILE_NUMBER),
        "max_steps": pick(st.integers(1, 5), st.sampled_from([0, -3, 2.5, math.inf, "5"])),
    }
    env = {
        "max_round_trips": pick(st.integers(1, 3), st.sampled_from([0, -2, 1.5, math.nan])),
        "tol": pick(st.one_of(st.none(), st.floats(0, 1e-3)), st.sampled_from([-1e-6, math.nan, "tight"])),
        "dtype": pick(st.sampled_from(["complex64", "complex128"]), st.sampled_from(["float32", None])),
        "compile": False,
        "reward_center": pick(FINITE, HOSTILE_NUMBER.filter(lambda v: v not in (0.0, -1.0, 1e12))),
        "reward_scale": pick(st.floats(1e-3, 10), HOSTILE_NUMBER.filter(lambda v: v != 1e12)),
        "physics": {"n": pick(st.sampled_from([16, 32]), st.sampled_from([8, 48, 0, "64"])),
                    "z_steps": pick(st.just(1), st.sampled_from([0, -1, 1.5])),
                    "T": pick(st.floats(10, 100), HOSTILE_NUMBER.filter(lambda v: v != 1e12)),
                    "g0": pick(st.floats(0, 3), st.sampled_from([-1.0, math.nan]))},
    }
    num_envs = pick(st.integers(1, 3), st.sampled_from([0, -2, 2.0, True]))
    return env, stage, num_envs


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(env_configs(), st.integers(0, 2**16))
def test_fuzz_env_configs_give_a_working_env_or_a_named_error(config, seed):
    env_cfg, stage_cfg, num_envs = config
    try:
        env = make_env(env_cfg, stage_cfg, num_envs, seed)
    except ValueError as err:
        assert KEY.match(str(err)), f"error does not name a config key: {err}"
        return
    td = env.reset()
    for _ in range(2):
        td = env.rand_step(td)
        for key in ("fields", "angles", "r"):
            assert torch.isfinite(td["next", key]).all()
        assert torch.isfinite(td["next", "reward"]).all()
        assert env.observation_spec.is_in(td["next"].select(*env.observation_spec.keys(True, True)))
        td = td["next"]


@pytest.mark.parametrize("stage_cfg", [
    {"controlled": ["alpha2", "alpha_p"], "steps_deg": [0.5, 30.0], "K": [-0.3, 0.4], "init_fields": "noise",
     "init_angles_deg": {"alpha1": [-90, 90], "alpha2": 3.0, "alpha3": 28.0, "alpha_p": [80, 100]}, "max_steps": 2},
    {"controlled": list(ANGLE_NAMES), "steps_deg": [2.0] * 4, "K": 0.1, "init_fields": "sech", "sech_amplitude": 10.0,
     "init_angles_deg": {"alpha1": -24.0, "alpha2": 3.0, "alpha3": 28.0, "alpha_p": 88.0}, "max_steps": 3},
])
def test_extreme_but_valid_configs_pass_check_env_specs(stage_cfg):
    env_cfg = {"max_round_trips": 2, "tol": None, "dtype": "complex64", "compile": False, "reward_center": 0.1,
               "reward_scale": 0.1, "physics": {"n": 32, "z_steps": 1}}
    check_env_specs(make_env(env_cfg, stage_cfg, 2, seed=0))


# ----------------------------------------------------------------------------- no NaN in the replay buffer
def test_a_nan_field_raises_before_it_reaches_the_replay_buffer():
    """A cavity whose field turns NaN mid-collection stops the collector with NonFiniteFieldError
    (naming the cavity); the buffer keeps only the finite transitions collected before."""
    from torchrl.collectors import Collector

    cfg = _compose(["experiment=smoke", "env.physics.n=32", "env.physics.z_steps=1", "env.max_round_trips=2"])
    env = make_env(OmegaConf.to_container(cfg.env, resolve=True), OmegaConf.to_container(cfg.stage, resolve=True),
                   4, seed=0)
    collector = Collector(env, None, frames_per_batch=8, total_frames=64)
    replay = make_replay("prioritized", 64, 4)
    batches = iter(collector)
    replay.extend(next(batches).reshape(-1))
    u = env.base_env.state.u.clone()
    u[2, 5] = complex(math.nan, 0.0)
    env.base_env.state.u = u  # the physics state of cavity 2 goes bad between two steps
    with pytest.raises(NonFiniteFieldError, match=r"cavity 2\b"):
        replay.extend(next(batches).reshape(-1))
    collector.shutdown()
    assert len(replay) == 8
    stored = replay.storage[:8]
    for key in ("fields", "angles", "r", ("next", "fields"), ("next", "reward")):
        assert torch.isfinite(stored[key]).all()
