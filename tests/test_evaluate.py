"""The evaluation protocol's success rule."""
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
