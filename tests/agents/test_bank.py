"""MaxQBank: per cavity, the model with the highest greedy Q-value acts."""
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Categorical

from laserrl.agents.bank import MaxQBank, MeanQ, make_bank_actor
from laserrl.agents.qnet import FieldQNet


def _qnet(seed, actions=3, n=64):
    torch.manual_seed(seed)
    return FieldQNet(actions, n=n)


def test_each_cavity_uses_the_model_with_the_highest_max_q():
    nets = [_qnet(0), _qnet(1), _qnet(2)]
    fields, angles = torch.randn(16, 4, 64), torch.randn(16, 4)
    with torch.no_grad():
        q = torch.stack([net(fields, angles) for net in nets])  # (3, 16, 3)
        chosen, model = MaxQBank(nets)(fields, angles)
    assert torch.equal(model, q.max(-1).values.argmax(0))
    for b in range(16):
        assert torch.equal(chosen[b], q[model[b], b])


def test_bank_actor_writes_the_greedy_action_of_the_chosen_model():
    nets = [_qnet(0), _qnet(1)]
    last = [m for m in nets[1].head if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():  # model 1's Q-values are far above model 0's everywhere
        last.bias.add_(100.0)
    actor = make_bank_actor(nets, Categorical(3))
    td = TensorDict(fields=torch.randn(8, 4, 64), angles=torch.randn(8, 4), batch_size=[8])
    with torch.no_grad():
        out = actor(td)
        q1 = nets[1](td["fields"], td["angles"])
    assert out["model"].tolist() == [1] * 8
    assert torch.equal(out["action"], q1.argmax(-1))


def test_models_must_agree_on_the_action_count():
    with pytest.raises(ValueError, match="same number of actions"):
        MaxQBank([_qnet(0, 3), _qnet(1, 9)])


def test_an_ensemble_averages_its_models_q_values_and_can_be_a_bank_member():
    nets = [_qnet(0), _qnet(1), _qnet(2)]
    fields, angles = torch.randn(8, 4, 64), torch.randn(8, 4)
    ensemble = MeanQ(nets)
    with torch.no_grad():
        q = torch.stack([net(fields, angles) for net in nets])
        assert torch.allclose(ensemble(fields, angles), q.mean(0))
        # a bank of a single model and an ensemble: per cavity the higher greedy Q wins
        single = _qnet(3)
        chosen, model = MaxQBank([single, ensemble])(fields, angles)
        both = torch.stack([single(fields, angles), q.mean(0)])
    assert ensemble.num_actions == 3
    assert torch.equal(model, both.max(-1).values.argmax(0))


def test_an_ensemble_needs_models_with_the_same_actions():
    with pytest.raises(ValueError, match="ensemble must have the same number of actions"):
        MeanQ([_qnet(0, 3), _qnet(1, 9)])
    with pytest.raises(ValueError, match="at least one"):
        MeanQ([])
