import math

import pytest
import torch
from tensordict import TensorDict

from laserrl.agents.dqn import (EpsilonSchedule, make_actor, make_loss, make_n_step, make_qnet, make_replay,
                                make_target_updater)
from laserrl.envs import LaserCavityEnv


def test_exponential_schedule_matches_formula_and_decays_monotonically():
    s = EpsilonSchedule(start=1.0, end=0.05, decay_frames=1000, kind="exponential")
    assert s(0) == pytest.approx(1.0)
    assert s(1000) == pytest.approx(0.05 + 0.95 * math.exp(-1))
    values = [s(f) for f in range(0, 20000, 500)]
    assert all(a > b for a, b in zip(values, values[1:]))
    assert values[-1] == pytest.approx(0.05, abs=1e-6)


def test_linear_schedule_reaches_end_and_stays():
    s = EpsilonSchedule(start=0.5, end=0.1, decay_frames=100, kind="linear")
    assert s(50) == pytest.approx(0.3)
    assert s(100) == pytest.approx(0.1) and s(10**6) == pytest.approx(0.1)


@pytest.mark.parametrize("kwargs, match", [({"kind": "cosine"}, "kind"), ({"start": 0.1, "end": 0.5}, "end"),
                                           ({"decay_frames": 0}, "decay_frames")])
def test_schedule_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        EpsilonSchedule(**kwargs)


@pytest.fixture(scope="module")
def parts():
    env = LaserCavityEnv(4, max_round_trips=2, seed=0)
    qnet = make_qnet(3, 256, (4, 4), 3, 4, (16,), 0.01)
    actor = make_actor(qnet, env.action_spec_unbatched)
    return env, qnet, actor


def test_double_dqn_loss_with_delayed_target(parts):
    env, qnet, actor = parts
    loss = make_loss(actor, env.action_spec_unbatched, gamma=0.9)
    assert loss.double_dqn and loss.delay_value
    with pytest.raises(ValueError, match="gamma"):
        make_loss(actor, env.action_spec_unbatched, gamma=1.5)


def test_soft_update_moves_target_towards_online_weights(parts):
    env, qnet, actor = parts
    loss = make_loss(actor, env.action_spec_unbatched, gamma=0.9)
    updater = make_target_updater(loss, "soft", tau=0.5)
    updater.init_()
    online = loss.value_network_params.flatten_keys()
    target = loss.target_value_network_params.flatten_keys()
    key = next(k for k in online.keys() if k.endswith("weight"))
    with torch.no_grad():
        online[key].add_(1.0)
    before = target[key].clone()
    updater.step()
    torch.testing.assert_close(target[key], before + 0.5, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="kind"):
        make_target_updater(loss, "polyak")


def test_prioritized_replay_updates_priorities_from_td_error():
    rb = make_replay("prioritized", 64, 8, alpha=1.0, beta=0.4)
    data = TensorDict(x=torch.arange(32.0), batch_size=[32])
    rb.extend(data)
    sample = rb.sample()
    sample.set("td_error", torch.full((8,), 100.0))
    rb.update_tensordict_priority(sample)
    hits = torch.zeros(32)
    for _ in range(50):
        hits[rb.sample()["index"]] += 1
    boosted = hits[sample["index"].unique()].mean()
    others = hits[[i for i in range(32) if i not in set(sample["index"].tolist())]].mean()
    assert boosted > 5 * others
    with pytest.raises(ValueError, match="replay.kind"):
        make_replay("fifo", 10, 2)


def _n_step_rollout(n_steps, gamma, batches=5, T=2):
    """A real rollout (4 cavities, 3-step episodes, auto-reset) fed to make_n_step in
    collector-sized batches of T steps; returns the rollout and the transitions it stored."""
    env = LaserCavityEnv(4, max_round_trips=2, max_steps=3, seed=0)
    torch.manual_seed(0)
    rollout = env.rollout(batches * T, break_when_any_done=False)  # (4, batches * T), time last
    transform = make_n_step(n_steps, gamma)
    stored = [transform.inv(rollout[:, i * T:(i + 1) * T]) for i in range(batches)]
    return rollout, torch.cat([s for s in stored if s is not None], -1)


@pytest.mark.parametrize("n_steps", [2, 3])
def test_n_step_transitions_sum_discounted_rewards_up_to_the_episode_end(n_steps):
    gamma = 0.9
    rollout, stored = _n_step_rollout(n_steps, gamma)
    reward = rollout["next", "reward"][..., 0]
    done = rollout["next", "done"][..., 0]
    steps = stored.shape[-1]
    assert steps == rollout.shape[-1] - n_steps  # the last n steps wait for the next batch
    for env in range(rollout.shape[0]):
        for t in range(steps):
            m = 1
            while m < n_steps and not bool(done[env, t + m - 1]):  # stop at the episode's last step
                m += 1
            want = sum(gamma**k * float(reward[env, t + k]) for k in range(m))
            assert float(stored["next", "reward"][env, t]) == pytest.approx(want, rel=1e-5)
            assert int(stored["steps_to_next_obs"][env, t]) == m
            assert torch.equal(stored["next", "fields"][env, t], rollout["next", "fields"][env, t + m - 1])
            assert torch.equal(stored["fields"][env, t], rollout["fields"][env, t])


def test_dqn_target_discounts_n_step_bootstrap_by_gamma_to_the_steps(parts):
    env, qnet, actor = parts
    gamma = 0.9
    loss = make_loss(actor, env.action_spec_unbatched, gamma=gamma)
    make_target_updater(loss, "hard", interval=1).init_()
    _, stored = _n_step_rollout(3, gamma)
    sample = stored.reshape(-1)
    target = loss.value_estimator.value_estimate(sample.clone(), target_params=loss.target_value_network_params)
    with torch.no_grad(), loss.target_value_network_params.to_module(loss.value_network):
        next_q = loss.value_network(sample["next"].clone())["action_value"]
    with torch.no_grad():  # double DQN: the online network picks the action, the target one values it
        online_best = actor(sample["next"].clone())["action_value"].argmax(-1, keepdim=True)
    boot = next_q.gather(-1, online_best)
    m = sample["steps_to_next_obs"].float().view_as(boot)
    want = sample["next", "reward"].view_as(boot) + gamma**m * boot  # the env never terminates
    assert bool((m > 1).any())
    torch.testing.assert_close(target.view_as(want), want, rtol=1e-5, atol=1e-5)


def test_n_steps_must_be_a_positive_integer():
    assert make_n_step(1, 0.9) is None  # the paper's one-step target: no transform
    for bad in (0, -2, 2.5, True, "3"):
        with pytest.raises(ValueError, match="agent.n_steps"):
            make_n_step(bad, 0.9)


def _agent(env, average_decay):
    from laserrl.agents.dqn import DQNAgent

    return DQNAgent.build(env.action_spec_unbatched, {"physics": {"n": 256}}, network={"channels": (4, 4), "kernel_size": 3, "pool": 4,
                          "hidden": (16,), "negative_slope": 0.01},
                          exploration={"start": 1.0, "end": 0.05, "decay_frames": 100.0}, gamma=0.9,
                          loss_function="smooth_l1", target={"kind": "soft", "tau": 0.01}, lr=1e-2, weight_decay=0.0,
                          lr_decay=1.0, lr_decay_updates=100, max_grad_norm=10.0, prioritized=False,
                          average_decay=average_decay)


def test_averaged_weights_follow_the_updates_as_an_exponential_moving_average():
    env = LaserCavityEnv(4, max_round_trips=2, seed=0)
    torch.manual_seed(0)
    agent = _agent(env, 0.5)
    assert agent.greedy is not agent.actor
    replay = make_replay("uniform", 64, 8)
    td = env.rollout(4, agent.policy)
    replay.extend(td.reshape(-1))
    key = next(k for k in agent.qnet.state_dict() if k.endswith("weight"))
    agent.restart_average()
    start = agent.qnet.state_dict()[key].clone()
    agent.update(replay)  # the first update copies the weights
    first = agent.qnet.state_dict()[key].clone()
    torch.testing.assert_close(agent.model_weights()[key], first)
    agent.update(replay)
    second = agent.qnet.state_dict()[key]
    torch.testing.assert_close(agent.model_weights()[key], 0.5 * first + 0.5 * second)
    assert not torch.equal(first, start) and not torch.equal(second, first)
    # the greedy actor acts with the average, not the online network
    with torch.no_grad():
        obs = env.reset()
        q_avg = agent.greedy(obs.clone())["action_value"]
        q_online = agent.actor(obs.clone())["action_value"]
    assert not torch.allclose(q_avg, q_online)
    # without averaging the greedy actor is the online one
    plain = _agent(env, None)
    assert plain.greedy is plain.actor and plain.averaged is None


@pytest.mark.parametrize("decay", [0.0, 1.0, 1.5, float("nan")])
def test_average_decay_outside_0_1_is_named(decay):
    from laserrl.validate import ConfigError

    with pytest.raises(ConfigError, match="agent.average_decay"):
        _agent(LaserCavityEnv(1, max_round_trips=2, seed=0), decay)


def test_a_run_with_averaged_weights_saves_and_exports_the_average(tmp_path):
    """The run's model/ holds the weight average; the checkpoint keeps the online weights for
    resuming, and exporting the checkpoint gives the average again."""
    from hydra import compose, initialize_config_dir

    from laserrl.checkpoint import load_checkpoint
    from laserrl.model import export_checkpoint, load_model
    from laserrl.paths import CONF_DIR
    from laserrl.train import train

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            "experiment=smoke", "env.physics.n=64", "env.physics.z_steps=2", "train.progress=false",
            "agent.average_decay=0.5", "eval.after_training=false", f"run_dir={tmp_path / 'run'}"])
    train(cfg)
    ckpt = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    model = load_model(tmp_path / "run")
    assert all(torch.equal(model["qnet"][k], v) for k, v in ckpt["averaged_qnet"].items())
    assert any(not torch.equal(ckpt["qnet"][k], v) for k, v in ckpt["averaged_qnet"].items())
    exported = load_model(export_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt", tmp_path / "exported"))
    assert all(torch.equal(exported["qnet"][k], v) for k, v in ckpt["averaged_qnet"].items())
