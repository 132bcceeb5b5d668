"""The evaluation protocol's success rule."""
import pytest
import torch

from laserrl.evaluate import success_mask


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
