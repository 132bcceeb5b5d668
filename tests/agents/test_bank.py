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
    from laserrl.agents.qnet import RecurrentMeasuredQNet

    with pytest.raises(ValueError, match="a recurrent one .* keeps a state of its own"):
        MeanQ([RecurrentMeasuredQNet(3, bins=8), RecurrentMeasuredQNet(3, bins=8)])


class _Constant(torch.nn.Module):
    """A Q-network stand-in whose greedy action is ``action`` everywhere."""

    in_keys = ("fields", "angles")

    def __init__(self, action, actions=3):
        super().__init__()
        self.num_actions, self.action = actions, action

    def forward(self, fields, angles):
        q = torch.zeros(*fields.shape[:-2], self.num_actions)
        q[..., self.action] = 1.0
        return q


def _trial_models(bank, r_path, step_counts=None):
    """The model index the trial bank picks at each step for one cavity whose measured r runs ``r_path``."""
    out = []
    for t, r in enumerate(r_path):
        steps = t if step_counts is None else step_counts[t]
        _, model = bank(torch.zeros(1, 4, 8), torch.zeros(1, 4), torch.tensor([[r]]), torch.tensor([[steps]]))
        out.append(int(model[0]))
    return out


def test_trial_bank_moves_on_when_r_does_not_rise_and_keeps_a_model_whose_r_rises():
    from laserrl.agents.bank import TrialBank, TrialRule

    rule = TrialRule(steps=3, min_rise=0.01, lock_r=0.15)
    flat = [0.05] * 8  # r never rises: each model gets 3 steps, then the next (cyclically)
    assert _trial_models(TrialBank([_Constant(0), _Constant(1), _Constant(2)], rule), flat) == [0, 0, 0, 1, 1, 1, 2, 2]
    rising = [0.05 + 0.01 * t for t in range(8)]  # r rises by 0.03 over every trial: model 0 stays
    assert _trial_models(TrialBank([_Constant(0), _Constant(1)], rule), rising) == [0] * 8
    # locked (r >= lock_r) with model 1: it stays although r no longer rises, and a new episode starts at model 0
    locked = [0.05, 0.05, 0.05, 0.05, 0.16, 0.16, 0.16, 0.16, 0.16, 0.05]
    steps = list(range(9)) + [0]
    assert _trial_models(TrialBank([_Constant(0), _Constant(1)], rule), locked, steps) == [0, 0, 0, 1, 1, 1, 1, 1, 1, 0]


def test_trial_actor_acts_with_the_model_on_trial_per_cavity():
    from laserrl.agents.bank import TrialRule, make_trial_actor

    actor = make_trial_actor([_Constant(0), _Constant(2)], Categorical(3), TrialRule(steps=1, min_rise=0.01))
    td = TensorDict(fields=torch.zeros(2, 4, 8), angles=torch.zeros(2, 4), r=torch.tensor([[0.05], [0.05]]),
                    step_count=torch.tensor([[0], [0]]), batch_size=[2])
    with torch.no_grad():
        assert actor(td.clone())["action"].tolist() == [0, 0]
        td["step_count"] += 1
        td["r"] = torch.tensor([[0.05], [0.07]])  # cavity 1's r rose over its one-step trial, cavity 0's did not
        out = actor(td.clone())
    assert out["model"].tolist() == [1, 0] and out["action"].tolist() == [2, 0]


class _MeasuredConstant(_Constant):
    in_keys = ("spectrum", "energy", "angles")

    def forward(self, spectrum, energy, angles):
        return super().forward(spectrum[..., None], angles)


def test_trial_actor_of_measured_models_judges_them_by_the_readings_reward():
    from laserrl.agents.bank import TrialRule, make_trial_actor

    actor = make_trial_actor([_MeasuredConstant(0), _MeasuredConstant(2)], Categorical(3), TrialRule(steps=1, min_rise=0.01))
    td = TensorDict(spectrum=torch.zeros(1, 8), energy=torch.zeros(1, 1), angles=torch.zeros(1, 4),
                    r=torch.tensor([[0.05]]), r_measured=torch.tensor([[0.05]]), step_count=torch.tensor([[0]]), batch_size=[1])
    with torch.no_grad():
        actor(td.clone())
        td["step_count"] += 1
        td["r"] = torch.tensor([[0.5]])  # the paper's r (not measured) rose; the readings' did not
        assert actor(td.clone())["model"].tolist() == [1]


@pytest.mark.parametrize("key, value", [("steps", 0), ("min_rise", -0.1), ("lock_r", float("nan"))])
def test_trial_rule_names_a_bad_setting(key, value):
    from laserrl.agents.bank import TrialRule

    with pytest.raises(ValueError, match=f"bank_trial.{key}"):
        TrialRule(**{key: value})
