import pytest
import torch

from laserrl.agents import FieldQNet
from laserrl.checkpoint import CheckpointError
from laserrl.model import model_metadata, save_model
from laserrl.envs import action_to_deltas
from laserrl.warmstart import additive_head_mapping, head_mapping, warm_start


def test_head_mapping_inherits_the_old_action_that_moves_old_angles_alike():
    old, new = ["alpha1"], ["alpha1", "alpha2"]
    index = head_mapping(old, new)
    steps_new, steps_old = torch.ones(2), torch.ones(1)
    for a in range(9):
        moves_new = action_to_deltas(torch.tensor(a), steps_new)
        moves_old = action_to_deltas(index[a], steps_old)
        assert moves_new[0] == moves_old[0]
    # to four controllers, from two: alpha1 and alpha2 keep their moves
    index = head_mapping(new, ["alpha1", "alpha2", "alpha3", "alpha_p"])
    for a in range(81):
        moves = action_to_deltas(torch.tensor(a), torch.ones(4))
        assert torch.equal(action_to_deltas(index[a], torch.ones(2)), moves[:2])
    with pytest.raises(CheckpointError, match="missing"):
        head_mapping(["alpha3"], ["alpha1", "alpha2"])


def _checkpoint(tmp_path, qnet, controlled, head="joint"):
    config = {"env": {}, "agent": {"network": {"head": head}}, "stage": {"name": "s", "controlled": controlled, "steps_deg": [2.0] * len(controlled)}}
    return str(save_model(tmp_path / "c", qnet.state_dict(), model_metadata(config, qnet.num_actions)))


def test_grown_network_reproduces_old_q_values_and_copies_other_layers(tmp_path):
    torch.manual_seed(0)
    old = FieldQNet(3)
    path = _checkpoint(tmp_path, old, ["alpha1"])
    new = FieldQNet(9)
    warm_start(new, path, ["alpha2", "alpha1"])  # order of the new stage need not match
    fields, angles = torch.randn(5, 4, 256), torch.randn(5, 4)
    q_old, q_new = old(fields, angles), new(fields, angles)
    index = head_mapping(["alpha1"], ["alpha2", "alpha1"])
    torch.testing.assert_close(q_new, q_old[:, index])
    torch.testing.assert_close(new.features[0].weight, old.features[0].weight)


def test_incompatible_heads_are_refused(tmp_path):
    path = _checkpoint(tmp_path, FieldQNet(9), ["alpha1", "alpha2"])
    with pytest.raises(CheckpointError, match="9-action head"):
        warm_start(FieldQNet(3), path, ["alpha1"])


def test_grown_additive_head_keeps_the_old_angles_values_and_starts_new_angles_indifferent(tmp_path):
    """From two controlled angles to four with the additive head: V and alpha1's and alpha2's rows
    carry over, so every joint action is valued as the old action moving alpha1 and alpha2 alike."""
    torch.manual_seed(0)
    old, new = FieldQNet(9, head="additive"), FieldQNet(81, head="additive")
    path = _checkpoint(tmp_path, old, ["alpha1", "alpha2"], head="additive")
    controlled = ["alpha3", "alpha1", "alpha_p", "alpha2"]
    warm_start(new, path, controlled)
    fields, angles = torch.randn(5, 4, 256), torch.randn(5, 4)
    torch.testing.assert_close(new(fields, angles), old(fields, angles)[:, head_mapping(["alpha1", "alpha2"], controlled)])
    assert additive_head_mapping(["alpha1", "alpha2"], controlled).tolist() == [0, -1, -1, -1, 1, 2, 3, -1, -1, -1, 4, 5, 6]
    with pytest.raises(CheckpointError, match="missing"):
        additive_head_mapping(["alpha3"], ["alpha1"])


def test_a_joint_head_does_not_warm_start_an_additive_one(tmp_path):
    path = _checkpoint(tmp_path, FieldQNet(9), ["alpha1", "alpha2"])
    with pytest.raises(CheckpointError, match="joint Q-head"):
        warm_start(FieldQNet(9, head="additive"), path, ["alpha1", "alpha2"])
    path = _checkpoint(tmp_path / "a", FieldQNet(3, head="additive"), ["alpha1"], head="additive")
    with pytest.raises(CheckpointError, match="additive Q-head"):
        warm_start(FieldQNet(9), path, ["alpha1", "alpha2"])
