import math

import pytest
import torch
from tensordict import TensorDict

from laserrl.agents.dqn import EpsilonSchedule, make_actor, make_loss, make_qnet, make_replay, make_target_updater
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
