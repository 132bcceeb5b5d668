import math

import pytest
import torch

from laserrl.agents import FieldQNet
from laserrl.agents.qnet import AdditiveActionValues, MeasuredQNet, RecurrentMeasuredQNet
from laserrl.envs.actions import action_to_deltas, hold_action


@pytest.mark.parametrize("num_actions", [3, 9, 81])
def test_q_values_for_every_joint_action_and_any_leading_shape(num_actions):
    net = FieldQNet(num_actions)
    fields, angles = torch.randn(2, 5, 4, 256), torch.randn(2, 5, 4)
    q = net(fields, angles)
    assert q.shape == (2, 5, num_actions)
    # the same states flattened give the same values: no mixing across the batch
    torch.testing.assert_close(net(fields.reshape(10, 4, 256), angles.reshape(10, 4)), q.reshape(10, num_actions))


def test_angle_input_has_the_period_of_the_optics():
    torch.manual_seed(0)
    net = FieldQNet(3)
    fields, angles = torch.randn(4, 4, 256), torch.rand(4, 4) * math.pi - math.pi / 2
    torch.testing.assert_close(net(fields, angles + math.pi), net(fields, angles), atol=1e-5, rtol=1e-5)
    assert not torch.allclose(net(fields, angles + 0.3), net(fields, angles))


def test_fields_drive_the_output():
    torch.manual_seed(0)
    net = FieldQNet(3)
    angles = torch.zeros(2, 4)
    assert not torch.allclose(net(torch.zeros(2, 4, 256), angles), net(torch.ones(2, 4, 256), angles))


@pytest.mark.parametrize("kwargs, match", [({"num_actions": 0}, "num_actions"), ({"num_actions": 3, "kernel_size": 4}, "kernel_size"),
                                           ({"num_actions": 3, "pool": 4, "channels": (8, 8, 8, 8, 8)}, "pool")])
def test_invalid_sizes_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FieldQNet(**kwargs)


def _recurrent_inputs(B, T, bins=8, points=4, gru_size=6, seed=0):
    from tensordict import TensorDict

    g = torch.Generator().manual_seed(seed)
    td = TensorDict(spectrum=torch.rand(B, T, bins, generator=g), energy=torch.rand(B, T, 1, generator=g) + 0.1,
                    autocorrelation=torch.rand(B, T, points, generator=g), angles=torch.rand(B, T, 4, generator=g) - 0.5,
                    recurrent_state=torch.zeros(B, T, 1, gru_size), is_init=torch.zeros(B, T, 1, dtype=torch.bool),
                    batch_size=[B, T])
    td["is_init"][:, 0] = True
    if T > 3:
        td["is_init"][0, 3] = True  # a new episode within the first sequence
    return td


def test_recurrent_qnet_over_a_sequence_equals_stepping_it():
    # learning runs the GRU over stored sequences; acting runs it one step at a time, carrying the state
    from torchrl.modules import set_recurrent_mode

    from laserrl.agents.qnet import RecurrentMeasuredQNet

    torch.manual_seed(0)
    net = RecurrentMeasuredQNet(5, bins=8, points=4, gru_size=6, hidden=(16, 12))
    module, td = net.td_module(), _recurrent_inputs(3, 7)
    with set_recurrent_mode(True):
        q_sequence = module(td.clone())["action_value"]
    state, steps = torch.zeros(3, 1, 6), []
    for t in range(7):
        out = module(td[:, t].clone().set("recurrent_state", state))
        steps.append(out["action_value"])
        state = out["next", "recurrent_state"]
    torch.testing.assert_close(torch.stack(steps, 1), q_sequence)
    assert q_sequence.shape == (3, 7, 5)


def test_recurrent_qnet_remembers_what_came_before():
    from laserrl.agents.qnet import RecurrentMeasuredQNet

    torch.manual_seed(0)
    net = RecurrentMeasuredQNet(5, bins=8, points=4, gru_size=6, hidden=(16,))
    module = net.td_module()
    a, b = _recurrent_inputs(2, 2, seed=1), _recurrent_inputs(2, 2, seed=2)
    b[:, 1] = a[:, 1]  # the same second observation after different first ones
    q = []
    for td in (a, b):
        first = module(td[:, 0].clone())
        q.append(module(td[:, 1].clone().set("recurrent_state", first["next", "recurrent_state"]))["action_value"])
    assert not torch.allclose(q[0], q[1])
    # ... and forgets at the start of an episode
    restart = [module(td[:, 1].clone().set("is_init", torch.ones(2, 1, dtype=torch.bool))
                      .set("recurrent_state", torch.randn(2, 1, 6)))["action_value"] for td in (a, b)]
    torch.testing.assert_close(restart[0], restart[1])


def test_recurrent_qnet_runs_only_as_a_tensordict_module():
    from laserrl.agents.qnet import RecurrentMeasuredQNet

    net = RecurrentMeasuredQNet(3, bins=8)
    with pytest.raises(TypeError, match="keeps a state between steps"):
        net(torch.zeros(1, 8), torch.ones(1, 1), torch.zeros(1, 4))
    with pytest.raises(ValueError, match="gru_size"):
        RecurrentMeasuredQNet(3, bins=8, gru_size=0)


def test_additive_head_sums_one_value_per_move_of_each_angle():
    """Q(s, a) = V + sum_j (A_j(d_j) - mean A_j) for joint action a = (d_1, ..., d_m), in the env's
    action encoding; its greedy joint action is each angle's best move, all-hold where holding is."""
    torch.manual_seed(0)
    m = 3
    head = AdditiveActionValues(m)
    x = torch.randn(6, 1 + 3 * m)
    q = head(x)
    assert q.shape == (6, 3**m)
    v, adv = x[:, 0], x[:, 1:].reshape(6, m, 3)
    for a in range(3**m):
        moves = action_to_deltas(torch.tensor(a), torch.ones(m)).long() + 1  # 0 down, 1 hold, 2 up
        expected = v + sum(adv[:, j, moves[j]] - adv[:, j].mean(-1) for j in range(m))
        torch.testing.assert_close(q[:, a], expected)
    best = q.argmax(-1)
    torch.testing.assert_close(action_to_deltas(best, torch.ones(m)).long() + 1, adv.argmax(-1))
    x[:, 1:].reshape(6, m, 3)[:, :, 1] += 10.0  # holding is every angle's best move
    assert (head(x).argmax(-1) == hold_action(m)).all()
    with pytest.raises(ValueError, match="reads 10 values"):
        head(torch.randn(2, 7))


@pytest.mark.parametrize("make", [
    lambda n, head: FieldQNet(n, head=head),
    lambda n, head: MeasuredQNet(n, bins=8, history=2, hidden=(16,), head=head),
    lambda n, head: RecurrentMeasuredQNet(n, bins=8, gru_size=6, hidden=(16, 12), head=head),
], ids=["fields", "measured", "gru"])
def test_every_network_takes_either_head_and_gives_one_value_per_joint_action(make):
    for n in (3, 9, 81):
        net = make(n, "additive")
        assert isinstance(net.head[-1], AdditiveActionValues) and net.head[-1].m == {3: 1, 9: 2, 81: 4}[n]
        assert net.head[-2].out_features == 1 + 3 * net.head[-1].m
        assert make(n, "joint").head[-1].out_features == n
    with pytest.raises(ValueError, match="power of 3"):
        make(8, "additive")
    with pytest.raises(ValueError, match="head must be one of"):
        make(9, "factored")
