import math

import pytest
import torch

from laserrl.agents import FieldQNet


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
