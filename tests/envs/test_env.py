"""LaserCavityEnv: specs, the paper's default task, actions, resets, seeding and errors."""
from __future__ import annotations

import itertools
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from laserrl.envs import (
    ANGLE_NAMES,
    LaserCavityEnv,
    action_to_deltas,
    centred_reward,
    deltas_to_action,
    hold_action,
    num_actions,
    wrap_angle,
)
from laserrl.physics import NonFiniteFieldError, reward_terms

FAST = dict(max_round_trips=3)  # a few round trips per agent step keep the env tests fast


def fixed_angles(alpha1=-30.0, alpha2=3.0, alpha3=28.0, alpha_p=88.0):
    return {"alpha1": alpha1, "alpha2": alpha2, "alpha3": alpha3, "alpha_p": alpha_p}


def step(env, td, action):
    td = td.clone()
    td["action"] = torch.as_tensor(action, dtype=torch.int64).reshape(env.batch_size)
    return env.step(td)


# ----------------------------------------------------------------------------- specs
def test_check_env_specs_default_task():
    check_env_specs(LaserCavityEnv(batch_size=3, max_round_trips=5, seed=0))


def test_check_env_specs_four_controllers():
    env = LaserCavityEnv(batch_size=2, controlled=ANGLE_NAMES, steps_deg=(0.5,) * 4, max_round_trips=3, seed=0)
    assert env.action_spec.space.n == 81
    check_env_specs(env)


# ----------------------------------------------------------------------------- default task
def test_default_task_is_the_papers(sech_np):
    env = LaserCavityEnv(batch_size=6, seed=1, **FAST)
    assert env.task.num_actions == 3 and env.action_spec.space.n == 3
    assert env.task.controlled == ("alpha1",) and env.task.steps_deg == (2.0,)
    td = env.reset()
    torch.testing.assert_close(env.K, torch.full((6,), 0.1, dtype=torch.float64))
    ang = env.angles_deg()
    assert ang.shape == (6, 4)
    torch.testing.assert_close(ang[:, 1:], torch.tensor([[3.0, 28.0, 88.0]], dtype=torch.float64).expand(6, 3))
    assert ((ang[:, 0] >= -40.0) & (ang[:, 0] <= -10.0)).all()
    assert len(set(ang[:, 0].tolist())) == 6  # sampled per cavity
    u, v = env.fields()
    expected = torch.as_tensor(sech_np, dtype=torch.complex64).expand(6, -1)
    torch.testing.assert_close(u, expected, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(v, expected, rtol=1e-6, atol=1e-7)
    # the observation is (Re u, Im u, Re v, Im v) and the angles in radians
    obs = td["fields"]
    assert obs.shape == (6, 4, 256) and obs.dtype == torch.float32
    torch.testing.assert_close(obs[:, 0], u.real)
    torch.testing.assert_close(obs[:, 3], v.imag)
    torch.testing.assert_close(td["angles"].double(), torch.deg2rad(ang), rtol=1e-6, atol=1e-6)
    assert (td["step_count"] == 0).all() and not td["done"].any()


def test_K_is_not_observed():
    env = LaserCavityEnv(batch_size=2, seed=0, **FAST)
    td = env.reset()
    out = step(env, td, [1, 2])
    for t in (td, out, out["next"]):
        keys = {k if isinstance(k, str) else k[-1] for k in t.keys(True, True)}
        assert "K" not in keys
    assert "K" not in env.observation_spec.keys(True, True)


# ----------------------------------------------------------------------------- actions
@pytest.mark.parametrize("m", [1, 2, 3, 4])
def test_action_mapping_round_trip(m):
    steps = torch.arange(1, m + 1, dtype=torch.float64) * 0.5  # distinct steps expose digit mix-ups
    actions = torch.arange(num_actions(m))
    assert num_actions(m) == 3**m
    deltas = action_to_deltas(actions, steps)
    assert deltas.shape == (3**m, m)
    assert len({tuple(row) for row in deltas.tolist()}) == 3**m  # every action is a distinct move
    signs = deltas / steps
    assert set(signs.flatten().tolist()) <= {-1.0, 0.0, 1.0}
    torch.testing.assert_close(deltas, signs * steps)
    assert torch.equal(deltas_to_action(signs), actions)
    # all sign patterns are reached
    assert {tuple(int(s) for s in row) for row in signs.tolist()} == set(itertools.product((-1, 0, 1), repeat=m))
    hold = action_to_deltas(torch.tensor(hold_action(m)), steps)
    assert torch.equal(hold, torch.zeros(m, dtype=torch.float64))


def test_step_moves_controlled_angle_by_the_step():
    env = LaserCavityEnv(batch_size=3, init_angles_deg=fixed_angles(-30.0), seed=0, **FAST)
    td = env.reset()
    before = env.angles_deg()
    out = step(env, td, [0, 1, 2])  # decrease, hold, increase
    after = env.angles_deg()
    torch.testing.assert_close(after[:, 0] - before[:, 0], torch.tensor([-2.0, 0.0, 2.0], dtype=torch.float64),
                               rtol=0, atol=1e-9)
    torch.testing.assert_close(after[:, 1:], before[:, 1:], rtol=0, atol=0)
    torch.testing.assert_close(out["next", "angles"].double(), torch.deg2rad(after), rtol=1e-6, atol=1e-6)
    # the policy's action is kept in the root of the step output
    assert out["action"].tolist() == [0, 1, 2]


def test_four_controller_actions_move_each_angle():
    steps = (0.5, 1.0, 1.5, 2.0)
    env = LaserCavityEnv(batch_size=2, controlled=("alpha1", "alpha2", "alpha3", "alpha_p"), steps_deg=steps,
                         init_angles_deg=fixed_angles(15.0, -5.0, 20.0, 84.0), seed=0, **FAST)
    td = env.reset()
    signs = torch.tensor([[1, -1, 0, 1], [-1, 0, 1, -1]])
    step(env, td, deltas_to_action(signs))
    expected = torch.tensor([15.0, -5.0, 20.0, 84.0], dtype=torch.float64) + signs * torch.tensor(steps, dtype=torch.float64)
    torch.testing.assert_close(env.angles_deg(), expected, rtol=0, atol=1e-9)


def test_angles_wrap_modulo_180_degrees():
    env = LaserCavityEnv(batch_size=1, init_angles_deg=fixed_angles(89.0), seed=0, **FAST)
    env.reset()
    assert float(env.angles_deg()[0, 0]) == pytest.approx(89.0, abs=1e-9)
    out = step(env, env.reset(), [2])
    assert float(env.angles_deg()[0, 0]) == pytest.approx(-89.0, abs=1e-9)
    ang = out["next", "angles"]
    assert ((ang >= -math.pi / 2) & (ang < math.pi / 2)).all()
    step(env, out["next"], [0])  # and back across the boundary
    assert float(env.angles_deg()[0, 0]) == pytest.approx(89.0, abs=1e-9)


def test_wrap_angle_range_and_period():
    a = torch.linspace(-10, 10, 1001, dtype=torch.float64)
    w = wrap_angle(a)
    assert ((w >= -math.pi / 2) & (w < math.pi / 2)).all()
    k = (a - w) / math.pi
    torch.testing.assert_close(k, k.round(), rtol=0, atol=1e-9)  # differs by whole multiples of pi


# ----------------------------------------------------------------------------- resets
def test_partial_reset_only_touches_masked_cavities(sech_np):
    env = LaserCavityEnv(batch_size=3, seed=3, **FAST)
    td = env.reset()
    for a in ([2, 0, 2], [0, 2, 1]):
        td = step(env, td, a)["next"]
    u, v = env.fields()
    angles = env.angles_deg()
    assert td["step_count"].flatten().tolist() == [2, 2, 2]
    mask = torch.tensor([[True], [False], [True]])
    td.set("_reset", mask)
    out = env.reset(td)
    u2, v2 = env.fields()
    a2 = env.angles_deg()
    # cavity 1 is untouched, bit for bit
    assert torch.equal(u2[1], u[1]) and torch.equal(v2[1], v[1]) and torch.equal(a2[1], angles[1])
    assert out["step_count"].flatten().tolist() == [0, 2, 0]
    # cavities 0 and 2 are back at the initial sech fields (which differ from the stepped ones)
    sech = torch.as_tensor(sech_np, dtype=torch.complex64)
    for i in (0, 2):
        assert not torch.equal(u2[i], u[i])
        torch.testing.assert_close(u2[i], sech, rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(v2[i], sech, rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(out["fields"][i, 0], sech.real, rtol=1e-6, atol=1e-7)
    # the env's own step counters continue: 0 -> 1 for the reset cavities, 2 -> 3 for cavity 1
    nxt = step(env, out, [1, 1, 1])["next"]
    assert nxt["step_count"].flatten().tolist() == [1, 3, 1]


def test_partial_reset_with_only_the_mask():
    env = LaserCavityEnv(batch_size=3, seed=4, **FAST)
    td = env.reset()
    step(env, td, [2, 2, 2])
    u, v = env.fields()
    env.reset(TensorDict({"_reset": torch.tensor([[True], [False], [True]])}, batch_size=[3]))
    u2, v2 = env.fields()
    assert torch.equal(u2[1], u[1]) and torch.equal(v2[1], v[1])
    assert not torch.equal(u2[0], u[0]) and not torch.equal(u2[2], u[2])
    nxt = step(env, env.reset(TensorDict({"_reset": torch.zeros(3, 1, dtype=torch.bool)}, batch_size=[3])), [1, 1, 1])
    assert nxt["next", "step_count"].flatten().tolist() == [1, 2, 1]


# ----------------------------------------------------------------------------- seeding
def test_same_seed_same_reset_angles():
    a = LaserCavityEnv(batch_size=4, seed=11, **FAST).reset()["angles"]
    b = LaserCavityEnv(batch_size=4, seed=11, **FAST).reset()["angles"]
    c = LaserCavityEnv(batch_size=4, seed=12, **FAST).reset()["angles"]
    assert torch.equal(a, b)
    assert not torch.equal(a[:, 0], c[:, 0])


def test_set_seed_then_reset_reproduces():
    env = LaserCavityEnv(batch_size=4, seed=0, **FAST)
    env.set_seed(123)
    first = env.reset()["angles"]
    second = env.reset()["angles"]
    assert not torch.equal(first, second)  # the generator advances
    env.set_seed(123)
    assert torch.equal(env.reset()["angles"], first)


# ----------------------------------------------------------------------------- step outputs
def test_truncation_after_max_steps():
    env = LaserCavityEnv(batch_size=2, max_steps=2, seed=0, **FAST)
    td = env.reset()
    out1 = step(env, td, [1, 1])["next"]
    assert not out1["done"].any() and not out1["truncated"].any()
    out2 = step(env, out1, [1, 1])["next"]
    assert out2["done"].all() and out2["truncated"].all() and not out2["terminated"].any()


def test_reward_is_r_of_the_new_state():
    env = LaserCavityEnv(batch_size=3, seed=5, **FAST)
    td = env.reset()
    out = step(env, td, [0, 1, 2])["next"]
    u, v = env.fields()
    r = reward_terms(u, v, env.params)[2].to(torch.float32).unsqueeze(-1)
    torch.testing.assert_close(out["reward"], r, rtol=1e-6, atol=0)
    torch.testing.assert_close(out["r"], r, rtol=1e-6, atol=0)
    # the state did change during the step, so the reward is not the reset r
    assert not torch.allclose(out["r"], td["r"], rtol=1e-4, atol=0)
    assert (out["round_trips"] >= 1).all() and (out["round_trips"] <= 3).all()


def test_move_cost_is_taken_from_the_reward_of_steps_that_turn_a_plate_and_r_is_unchanged():
    kw = dict(batch_size=3, seed=5, controlled=ANGLE_NAMES, steps_deg=(0.5,) * 4, **FAST)
    hold = hold_action(4)
    actions = [hold, 0, hold + 1]  # hold; all four plates down; alpha1 alone up
    plain = LaserCavityEnv(**kw)
    costly = LaserCavityEnv(move_cost=0.02, **kw)
    a = step(plain, plain.reset(), actions)["next"]
    b = step(costly, costly.reset(), actions)["next"]
    torch.testing.assert_close(b["r"], a["r"])  # the same cavities: the cost is not physics
    torch.testing.assert_close(b["reward"], a["r"] - torch.tensor([[0.0], [0.02], [0.02]]))


def test_move_cost_from_charges_only_moves_that_start_at_or_above_it_also_after_a_partial_reset():
    kw = dict(batch_size=4, seed=3, controlled=ANGLE_NAMES, steps_deg=(0.5,) * 4, **FAST)
    hold = hold_action(4)
    actions = torch.tensor([0, 0, hold, 0])  # three move, one holds
    reset_first = TensorDict(_reset=torch.tensor([[True], [False], [False], [False]]), batch_size=[4])

    def run(env):  # three steps with a reset of cavity 0 before the third: (r_before, r_after, reward) per step
        td = env.reset()
        rows = []
        for i in range(3):
            if i == 2:  # the reset output holds only the reset cavity's entries
                fresh = env.reset(reset_first.clone())
                td = td.update(fresh.exclude("r")).set("r", torch.where(reset_first["_reset"], fresh["r"], td["r"]))
            before = td["r"].clone()
            td = step(env, td, actions)["next"]
            rows.append((before, td["r"], td["reward"]))
            td = td.exclude("reward", "done", "terminated", "truncated")
        return rows

    plain = run(LaserCavityEnv(**kw))
    threshold = float(torch.cat([r for _, r, _ in plain[:2]]).median())  # some moves start above it, some below
    costly = run(LaserCavityEnv(move_cost=0.02, move_cost_from=threshold, **kw))
    moved = (actions != hold).unsqueeze(-1)
    charged = 0
    for (before, r, reward), (_, r_c, reward_c) in zip(plain, costly):
        torch.testing.assert_close(r_c, r)
        due = moved & (before >= threshold)
        charged += int(due.sum())
        torch.testing.assert_close(reward_c, r - 0.02 * due.float())
    assert 0 < charged < 9  # the threshold splits the nine moves


def test_fine_steps_turn_the_plates_from_states_whose_reward_reaches_fine_from_also_after_a_partial_reset():
    kw = dict(batch_size=4, seed=3, controlled=ANGLE_NAMES, steps_deg=(1.0,) * 4, **FAST)
    actions = torch.full((4,), num_actions(4) - 1)  # every plate up by one step
    reset_first = TensorDict(_reset=torch.tensor([[True], [False], [False], [False]]), batch_size=[4])

    def run(env):  # three steps, cavity 0 reset before the third: (r before the step, angle turns in deg) per step
        td = env.reset()
        rows = []
        for i in range(3):
            if i == 2:
                fresh = env.reset(reset_first.clone())
                td = td.update(fresh.exclude("r")).set("r", torch.where(reset_first["_reset"], fresh["r"], td["r"]))
            before, angles = td["r"].clone(), env.angles_deg()
            td = step(env, td, actions)["next"]
            rows.append((before, (env.angles_deg() - angles + 90) % 180 - 90))  # alpha_p wraps at 90 deg
            td = td.exclude("reward", "done", "terminated", "truncated")
        return rows

    plain = run(LaserCavityEnv(**kw))
    level = float(torch.cat([r for r, _ in plain]).median())  # some turns start above it, some below
    fine = run(LaserCavityEnv(fine_steps_deg=(0.25,) * 4, fine_from=level, **kw))
    near = torch.cat([r >= level for r, _ in fine])
    assert 0 < int(near.sum()) < 12
    turns = torch.cat([t for _, t in fine])
    torch.testing.assert_close(turns, torch.where(near, 0.25, 1.0).expand(-1, 4).to(turns))
    for _, t in plain:
        torch.testing.assert_close(t, torch.ones_like(t))


@pytest.mark.parametrize("settings, match", [
    (dict(fine_steps_deg=(0.25,)), "go together"), (dict(fine_from=0.3), "go together"),
    (dict(fine_steps_deg=(0.25, 0.25), fine_from=0.3), "fine_steps_deg"),
    (dict(fine_steps_deg=(0.0,), fine_from=0.3), "fine_steps_deg"), (dict(fine_steps_deg=(0.25,), fine_from=math.nan), "fine_from")])
def test_bad_fine_steps_are_named(settings, match):
    with pytest.raises(ValueError, match=match):
        LaserCavityEnv(batch_size=1, **settings)


@pytest.mark.parametrize("start", [math.nan, "0.3", True])
def test_bad_move_cost_from_is_named(start):
    with pytest.raises(ValueError, match="move_cost_from"):
        LaserCavityEnv(batch_size=1, move_cost=0.02, move_cost_from=start)


@pytest.mark.parametrize("cost", [-0.1, math.inf, "0.1", True])
def test_bad_move_cost_is_named(cost):
    with pytest.raises(ValueError, match="move_cost"):
        LaserCavityEnv(batch_size=1, move_cost=cost)


def test_nan_field_names_the_cavity():
    env = LaserCavityEnv(batch_size=3, seed=0, **FAST)
    td = env.reset()
    env.state.u[1] = float("nan")
    with pytest.raises(NonFiniteFieldError, match=r"cavity 1\b") as info:
        step(env, td, [1, 1, 1])
    assert info.value.cavities == [1]


# ----------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(controlled=("alpha9",)), r"controlled"),
        (dict(steps_deg=(-1.0,)), r"steps_deg"),
        (dict(steps_deg=(1.0, 2.0)), r"steps_deg"),
        (dict(init_angles_deg={"alpha1": -20.0, "alpha2": 3.0, "alpha3": 28.0}), r"init_angles_deg.*alpha_p"),
        (dict(K=(0.3, 0.1)), r"\bK\b"),
        (dict(init_fields="foo"), r"init_fields"),
        (dict(max_steps=0), r"max_steps"),
        (dict(max_round_trips=0), r"max_round_trips"),
        (dict(dtype="float16"), r"dtype"),
        (dict(foo_bar=1), r"foo_bar"),
        (dict(batch_size=0), r"batch_size"),
    ],
    ids=["controlled", "steps-negative", "steps-length", "init-missing", "K-range", "init_fields", "max_steps",
         "max_round_trips", "dtype", "unknown-kwarg", "batch_size"],
)
def test_invalid_task_raises_naming_the_field(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        LaserCavityEnv(**kwargs)


# ----------------------------------------------------------------------------- transforms & options
def test_centred_reward_transform():
    base = LaserCavityEnv(batch_size=3, seed=2, **FAST)
    env = TransformedEnv(base, centred_reward(center=0.1, scale=0.1))
    td = env.reset()
    td["action"] = torch.tensor([0, 1, 2])
    out = env.step(td)["next"]
    u, v = base.fields()
    raw = reward_terms(u, v, base.params)[2].to(torch.float32).unsqueeze(-1)
    torch.testing.assert_close(out["r"], raw, rtol=1e-6, atol=0)
    torch.testing.assert_close(out["reward"], (raw - 0.1) / 0.1, rtol=1e-5, atol=1e-6)


def test_noise_initial_fields_are_seeded():
    def fields(seed):
        env = LaserCavityEnv(batch_size=3, init_fields="noise", seed=seed, **FAST)
        env.reset()
        return env.fields()

    u, v = fields(21)
    u_same, v_same = fields(21)
    u_other, _ = fields(22)
    assert torch.equal(u, u_same) and torch.equal(v, v_same)
    assert not torch.equal(u, u_other)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        assert not torch.allclose(u[i], u[j])
    assert not torch.allclose(u, v)
    # complex Gaussian noise of standard deviation noise_scale = 0.1 per component
    comps = torch.cat([torch.view_as_real(u).flatten(), torch.view_as_real(v).flatten()])
    assert float(comps.std()) == pytest.approx(0.1, rel=0.1)
    assert abs(float(comps.mean())) < 0.02


def test_K_range_is_sampled_per_cavity():
    env = LaserCavityEnv(batch_size=8, K=(-0.2, 0.4), seed=9, **FAST)
    td = env.reset()
    K = env.K
    assert K.shape == (8,)
    assert ((K >= -0.2) & (K <= 0.4)).all()
    assert len(set(K.tolist())) == 8
    step(env, td, [1] * 8)
    assert torch.equal(env.K, K)  # the disturbance is not changed by a step
    env.reset()
    assert not torch.equal(env.K, K)  # but is resampled at reset


def test_a_snapshot_continues_the_episodes_in_flight():
    env = LaserCavityEnv(3, max_round_trips=3, seed=4)
    td = env.reset()
    td = step(env, td, [0, 1, 2])["next"]
    saved = env.snapshot()
    after = step(env, td, [2, 2, 0])["next"]
    other = LaserCavityEnv(3, max_round_trips=3, seed=99)
    other.continue_from(saved)
    again = other.reset()  # the first full reset returns the saved state, not a new draw
    assert torch.equal(again["fields"], td["fields"]) and torch.equal(again["step_count"], td["step_count"])
    assert torch.equal(step(other, again, [2, 2, 0])["next"]["fields"], after["fields"])
    assert torch.equal(other._rng.get_state(), env._rng.get_state())
    fresh = other.reset()  # later resets sample as usual
    assert int(fresh["step_count"].sum()) == 0


def test_a_snapshot_of_another_env_is_refused_by_name():
    saved = LaserCavityEnv(2, max_round_trips=3).snapshot()
    with pytest.raises(ValueError, match=r"the saved env state does not fit this env \(u: expected"):
        LaserCavityEnv(3, max_round_trips=3).continue_from(saved)
    with pytest.raises(ValueError, match="the saved env state does not fit this env"):
        LaserCavityEnv(2, max_round_trips=3).continue_from({"state": {}})
