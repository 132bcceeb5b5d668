"""The evaluation protocol's success rule."""
import pytest
import torch

from laserrl.evaluate import success_mask, success_rate


def test_final_reward_rule_without_hold():
    r = torch.tensor([[0.0, 0.2, 0.05], [0.0, 0.0, 0.19]])
    assert success_mask(r, 0.18, None).tolist() == [False, True]


def test_lock_then_hold_rule():
    r = torch.tensor([
        [0.0, 0.16, 0.12, 0.11],   # locks at step 2, holds >= 0.1: success
        [0.0, 0.16, 0.05, 0.16],   # drops below 0.1 after the first lock, relocks at the end: success
        [0.0, 0.16, 0.12, 0.05],   # loses the lock at the last step: failure
        [0.0, 0.14, 0.14, 0.14],   # never reaches 0.15: failure
        [0.2, 0.2, 0.2, 0.2],      # locked from the first step: success
    ])
    assert success_mask(r, 0.15, 0.1).tolist() == [True, True, False, False, True]


def test_hold_value_gap_splits_steps_taken_from_a_lock_from_the_others():
    from laserrl.evaluate import hold_value_gap

    # two controlled angles: 9 actions, the all-hold action is 4 (both digits 1)
    q = torch.zeros(1, 4, 9)
    q[0, :, 0] = torch.tensor([1.0, 2.0, 3.0, 5.0])  # the best action, above a hold valued 0
    r = torch.tensor([[0.2, 0.0, 0.2, 0.0]])          # steps 1 and 3 are taken from a lock
    assert hold_value_gap(q, r, 0.15, 2) == {"from_lock": 2.0, "searching": 1.0}  # medians of (2, 5) and (1, 3)
    q[0, 3, 4] = 9.0                                  # holding valued best: gap 0 there
    assert hold_value_gap(q, r, 0.15, 2)["from_lock"] == 0.0
    assert hold_value_gap(q, torch.zeros(1, 4), 0.15, 2)["from_lock"] is None


def test_success_rate_of_9_in_10_meets_a_target_of_90_percent():
    success = torch.tensor([True] * 9 + [False])
    assert success_rate(success) >= 0.9 and success_rate(success) == 0.9
    assert success_rate(torch.zeros(3, dtype=torch.bool)) == 0.0


def test_nearest_model_of_a_bank_with_points_and_ranges():
    from laserrl.evaluate import nearest_model

    points = [-0.2, 0.0, 0.2, 0.4]
    assert [nearest_model(points, K) for K in (-0.2, -0.15, 0.05, 0.35, 0.4)] == [0, 0, 1, 3, 3]
    assert nearest_model(points, -0.1) == 0 and nearest_model(points, 0.3) == 2  # ties: the first model
    # a model fine-tuned over a K range serves the K inside it; outside, its range's centre counts
    ranged = [(-0.2, -0.1), 0.0, 0.2, (0.3, 0.4)]
    assert [nearest_model(ranged, K) for K in (-0.2, -0.15, -0.1, -0.05, 0.25, 0.3, 0.35)] == [0, 0, 0, 1, 2, 3, 3]
    assert nearest_model([0.0, (0.1, 0.5)], 0.12) == 1 and nearest_model([0.0, (0.2, 0.6)], 0.15) == 0


def test_a_bank_model_with_an_unusable_K_is_refused_by_path():
    from laserrl.checkpoint import CheckpointError
    from laserrl.evaluate import _stage_K

    assert _stage_K({"config": {"stage": {"K": [0.3, 0.1]}}}) == (0.1, 0.3)
    with pytest.raises(CheckpointError, match="m.pt has stage.K"):
        _stage_K({"path": "m.pt", "config": {"stage": {"K": "warm"}}})


def _hold_policy(env):
    from laserrl.envs.actions import hold_action

    def act(td):
        return td.set("action", torch.full(td.batch_size, hold_action(1), dtype=torch.int64))
    return act


@pytest.mark.parametrize("init_fields", ["sech", "noise"])
def test_eval_init_fields_sets_the_initial_fields_of_the_protocol(init_fields):
    from laserrl.evaluate import evaluate_policy

    env_cfg = {"num_envs": 2, "max_round_trips": 3, "tol": None, "dtype": "complex64", "compile": False,
               "reward_center": 0.1, "reward_scale": 0.1, "physics": {"n": 64, "z_steps": 2}}
    stage_cfg = {"name": "siso", "controlled": ["alpha1"], "steps_deg": [2.0], "K": 0.1, "init_fields": "sech",
                 "init_angles_deg": {"alpha1": [-40.0, -10.0], "alpha2": 3.0, "alpha3": 28.0, "alpha_p": 88.0},
                 "max_steps": 3}
    eval_cfg = {"steps": 2, "starts_deg": [-24.0], "success_r": 0.18, "repeats": 2, "init_fields": init_fields}
    paths = [p["reward_path"] for p in evaluate_policy(_hold_policy, env_cfg, stage_cfg, eval_cfg)["per_start"]]
    # the two copies of one start: identical from the sech fields, each with its own draw from noise
    assert (paths[0] == paths[1]) == (init_fields == "sech"), paths


def test_eval_on_a_cavity_other_than_the_trained_one():
    """eval.physics (laserrl-eval env.physics.KEY=...) changes the cavity evaluated on, and
    eval.json says which values changed; a bad value names its key."""
    from laserrl.evaluate import evaluate_policy

    env_cfg = {"num_envs": 2, "max_round_trips": 3, "tol": None, "dtype": "complex64", "compile": False,
               "reward_center": 0.1, "reward_scale": 0.1, "physics": {"n": 64, "z_steps": 2}}
    stage_cfg = {"name": "siso", "controlled": ["alpha1"], "steps_deg": [2.0], "K": 0.1, "init_fields": "sech",
                 "init_angles_deg": {"alpha1": [-40.0, -10.0], "alpha2": 3.0, "alpha3": 28.0, "alpha_p": 88.0},
                 "max_steps": 3}
    eval_cfg = {"steps": 2, "starts_deg": [-24.0], "success_r": 0.18}
    same = evaluate_policy(_hold_policy, env_cfg, stage_cfg, {**eval_cfg, "physics": {"g0": None}})
    other = evaluate_policy(_hold_policy, env_cfg, stage_cfg, {**eval_cfg, "physics": {"g0": 1.9, "D": None}})
    assert same["physics_changed"] == {} and other["physics_changed"] == {"g0": 1.9}
    assert same["per_start"][0]["reward_path"] == evaluate_policy(_hold_policy, env_cfg, stage_cfg, eval_cfg)["per_start"][0]["reward_path"]
    assert other["per_start"][0]["reward_path"] != same["per_start"][0]["reward_path"]  # more gain: another pulse
    with pytest.raises(ValueError, match="env.physics.g0"):
        evaluate_policy(_hold_policy, env_cfg, stage_cfg, {**eval_cfg, "physics": {"g0": -1.0}})


def test_eval_on_cavities_drawn_around_the_trained_one():
    """eval.physics_spread: every rollout on its own cavity within +-spread of the nominal one, listed in
    eval.json and seeded; a bad spread names eval.physics_spread."""
    from laserrl.evaluate import evaluate_policy
    from laserrl.physics.checks import CAVITY_KEYS
    from laserrl.physics.params import CavityParams

    env_cfg = {"num_envs": 2, "max_round_trips": 3, "tol": None, "dtype": "complex64", "compile": False,
               "reward_center": 0.1, "reward_scale": 0.1, "physics": {"n": 64, "z_steps": 2}}
    stage_cfg = {"name": "siso", "controlled": ["alpha1"], "steps_deg": [2.0], "K": 0.1, "init_fields": "noise",
                 "init_angles_deg": {"alpha1": [-40.0, -10.0], "alpha2": 3.0, "alpha3": 28.0, "alpha_p": 88.0},
                 "max_steps": 3}
    eval_cfg = {"steps": 2, "starts_deg": [-24.0], "success_r": 0.18, "repeats": 3, "seed": 5}
    nominal = evaluate_policy(_hold_policy, env_cfg, stage_cfg, eval_cfg)
    spread = evaluate_policy(_hold_policy, env_cfg, stage_cfg, {**eval_cfg, "physics_spread": 0.1})
    assert nominal["physics_spread"] is None and "cavity" not in nominal["per_start"][0]
    assert spread["physics_spread"] == 0.1
    cavities = [p["cavity"] for p in spread["per_start"]]
    base = CavityParams()
    for key in CAVITY_KEYS:
        values = [c[key] for c in cavities]
        assert all(abs(v / getattr(base, key) - 1) <= 0.1 + 1e-12 for v in values), (key, values)
        assert len(set(values)) == 3  # each rollout its own cavity
    assert all(n["reward_path"][0] != s["reward_path"][0] for n, s in zip(nominal["per_start"], spread["per_start"]))
    again = evaluate_policy(_hold_policy, env_cfg, stage_cfg, {**eval_cfg, "physics_spread": 0.1})
    assert [p["cavity"] for p in again["per_start"]] == cavities  # seeded
    with pytest.raises(ValueError, match="eval.physics_spread"):
        evaluate_policy(_hold_policy, env_cfg, stage_cfg, {**eval_cfg, "physics_spread": 0.7})


def test_eval_of_a_model_with_stacked_readings_starts_where_the_protocol_says():
    """With env.history the env is wrapped in TorchRL's CatFrames; the protocol's start angle and
    K still reach the cavities, and the angle path is the newest reading's."""
    from laserrl.evaluate import evaluate_policy

    env_cfg = {"num_envs": 2, "max_round_trips": 3, "tol": None, "dtype": "complex64", "compile": False,
               "reward_center": None, "reward_scale": None, "physics": {"n": 64, "z_steps": 2},
               "observation": "measured", "history": 3,
               "instruments": {"spectrum_bins": 16, "spectrum_span": 6.0, "autocorrelation_points": 16}}
    stage_cfg = {"name": "siso", "controlled": ["alpha1"], "steps_deg": [2.0], "K": 0.1, "init_fields": "sech",
                 "init_angles_deg": {"alpha1": [-40.0, -10.0], "alpha2": 3.0, "alpha3": 28.0, "alpha_p": 88.0},
                 "max_steps": 3}
    seen = {}

    def hold_and_look(env):
        act = _hold_policy(env)

        def policy(td):
            seen.setdefault("K", env.base_env.state.K.clone())
            return act(td)
        return policy

    out = evaluate_policy(hold_and_look, env_cfg, stage_cfg, {"steps": 2, "starts_deg": [50.0], "success_r": 0.18, "K": [-0.15]})
    assert [a[0] for a in out["per_start"][0]["angle_path_deg"]] == pytest.approx([50.0, 50.0], abs=1e-4)
    assert torch.allclose(seen["K"], torch.tensor([-0.15], dtype=torch.float64))


def test_held_steps_rejects_a_lock_that_comes_too_late_to_be_held_that_long():
    r = torch.tensor([
        [0.0, 0.16, 0.12, 0.11, 0.12],   # locks at index 1: held for 4 steps
        [0.0, 0.0, 0.0, 0.16, 0.16],     # locks at index 3: held for 2 steps (a sweep through a lock at the end)
        [0.16, 0.05, 0.0, 0.16, 0.16],   # an early lock lost, a late one held for 2 steps
    ])
    assert success_mask(r, 0.15, 0.1).tolist() == [True, True, True]
    assert success_mask(r, 0.15, 0.1, held_steps=2).tolist() == [True, True, True]
    assert success_mask(r, 0.15, 0.1, held_steps=3).tolist() == [True, False, False]
    assert success_mask(r, 0.15, 0.1, held_steps=5).tolist() == [False, False, False]
    assert success_mask(r, 0.15, 0.1, held_steps=9).tolist() == [False, False, False]  # longer than the episode
    # on random paths: the same as "some lock at index t <= T - held_steps, then r >= hold_r to the end"
    g = torch.Generator().manual_seed(0)
    paths = 0.2 * torch.rand(300, 12, generator=g)
    for held in (1, 4, 9):
        expected = [any(p[t] >= 0.15 and bool((p[t + 1:] >= 0.1).all()) for t in range(12 - held + 1)) for p in paths]
        assert success_mask(paths, 0.15, 0.1, held_steps=held).tolist() == expected


@pytest.mark.parametrize("eval_cfg, protocol, message", [
    ({"held_steps": 0}, {"hold_r": 0.1, "steps": 100}, "eval.held_steps"),
    ({"held_steps": 2.5}, {"hold_r": 0.1, "steps": 100}, "eval.held_steps"),
    ({"held_steps": 10}, {"hold_r": None, "steps": 20}, "eval.held_steps needs eval.hold_r"),
    ({"held_steps": 150}, {"hold_r": 0.1, "steps": 100}, "exceeds eval.steps"),
    ({"held_steps": 150, "steps": 100}, {"hold_r": 0.1, "steps": 200}, "exceeds eval.steps"),
])
def test_bad_held_steps_is_one_error_naming_it(eval_cfg, protocol, message):
    from laserrl.config import ConfigError
    from laserrl.evaluate import check_eval_config

    with pytest.raises(ConfigError, match=message):
        check_eval_config(eval_cfg, protocol)
    check_eval_config({**eval_cfg, "held_steps": 50, "steps": 100}, {"hold_r": 0.1})  # a good one passes
