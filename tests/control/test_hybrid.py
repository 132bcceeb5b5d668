"""The hybrid hands over to ESC and back by its documented rule (scripted policy, scripted r),
and deep RL as a controller moves the angles exactly as the env's actions do."""
import pytest
import torch
from tensordict import TensorDict

from laserrl.control import MODE_ESC, MODE_RL, DeepRL, ESCParams, Hybrid, HybridRule
from laserrl.envs.actions import action_to_deltas


class AlwaysIncrease:
    """Scripted policy: the 'increase' action of every controlled angle (digits 2)."""

    def __init__(self, m=1):
        self.action = sum(2 * 3**j for j in range(m))

    def __call__(self, td):
        return td.set("action", torch.full(td.batch_size, self.action, dtype=torch.int64))


def _obs(r):
    r = torch.as_tensor(r, dtype=torch.float32).reshape(-1, 1)
    B = r.shape[0]
    return TensorDict(fields=torch.zeros(B, 4, 8), angles=torch.zeros(B, 4), r=r, batch_size=[B])


def test_hybrid_hands_over_and_back_by_the_rule():
    rule = HybridRule(lock_r=0.15, lock_steps=2, unlock_r=0.1, unlock_steps=3)
    hybrid = Hybrid(DeepRL(AlwaysIncrease(), ["alpha1"], [2.0]), ESCParams(), rule, ["alpha1"], 2)
    # cavity 0: locks (2 steps >= 0.15), dips below 0.1 for 2 steps (stays with ESC), then 3 (back to RL)
    # cavity 1: only single steps >= 0.15, never 2 in a row: stays with deep RL
    r0 = [0.05, 0.16, 0.17, 0.20, 0.05, 0.05, 0.20, 0.05, 0.05, 0.05, 0.20, 0.20]
    r1 = [0.05, 0.16, 0.05, 0.16, 0.05, 0.16, 0.05, 0.16, 0.05, 0.16, 0.05, 0.16]
    expect0 = [0, 0, 1, 1, 1, 1, 1, 1, 1, 0, 0, 1]
    angles = torch.tensor([[-30.0, 3.0, 28.0, 88.0]] * 2, dtype=torch.float64)
    hybrid.reset(_obs([0.0, 0.0]), angles)
    modes = []
    for t in range(len(r0)):
        command = hybrid.act(_obs([r0[t], r1[t]]), angles)
        modes.append(hybrid.mode.tolist())
        rl_mode = hybrid.mode == MODE_RL
        # deep RL: +2 deg on alpha1; ESC: its estimate plus a dither of at most a = 1 deg; other angles held
        assert torch.allclose(command[rl_mode, 0], angles[rl_mode, 0] + 2.0)
        dither = command[:, 0].numpy() - hybrid.esc.theta[:, 0]
        assert (abs(dither[~rl_mode.numpy()]) <= 1.0 + 1e-9).all()
        assert torch.equal(command[:, 1:], angles[:, 1:])
    assert [m[0] for m in modes] == expect0
    assert [m[1] for m in modes] == [MODE_RL] * len(r1)
    assert hybrid.switches.tolist() == [3, 0]


def test_hybrid_with_settle_steps_waits_for_the_climb_to_end():
    """Above lock_r, ESC takes over only once r is within settle_rise of the best of the steps before."""
    rule = HybridRule(lock_r=0.15, lock_steps=1, unlock_r=0.1, unlock_steps=3, settle_steps=2, settle_rise=0.05)
    hybrid = Hybrid(DeepRL(AlwaysIncrease(), ["alpha1"], [2.0]), ESCParams(), rule, ["alpha1"], 2)
    # cavity 0 climbs past lock_r and levels off at step 4 (0.31 <= 1.05 * 0.30); cavity 1 keeps climbing by 10 %
    r0 = [0.05, 0.10, 0.20, 0.30, 0.31, 0.30]
    r1 = [0.05, 0.10, 0.16, 0.176, 0.194, 0.213]
    angles = torch.tensor([[-30.0, 3.0, 28.0, 88.0]] * 2, dtype=torch.float64)
    hybrid.reset(_obs([0.0, 0.0]), angles)
    modes = []
    for t in range(len(r0)):
        hybrid.act(_obs([r0[t], r1[t]]), angles)
        modes.append(hybrid.mode.tolist())
    assert [m[0] for m in modes] == [0, 0, 0, 0, 1, 1]
    assert [m[1] for m in modes] == [0] * 6
    # without the settle rule both engage at their first step above lock_r
    plain = Hybrid(DeepRL(AlwaysIncrease(), ["alpha1"], [2.0]), ESCParams(), HybridRule(lock_r=0.15), ["alpha1"], 2)
    plain.reset(_obs([0.0, 0.0]), angles)
    for t in range(3):
        plain.act(_obs([r0[t], r1[t]]), angles)
    assert plain.mode.tolist() == [MODE_ESC, MODE_ESC]


def test_esc_restarts_from_the_current_angles_on_engagement():
    hybrid = Hybrid(DeepRL(AlwaysIncrease(), ["alpha1"], [2.0]), ESCParams(amplitude_deg=0.5),
                    HybridRule(lock_steps=1), ["alpha1"], 1)
    angles = torch.tensor([[-24.0, 3.0, 28.0, 88.0]], dtype=torch.float64)
    hybrid.reset(_obs([0.0]), angles)
    command = hybrid.act(_obs([0.2]), angles)
    assert hybrid.mode.item() == MODE_ESC
    assert abs(float(command[0, 0]) - (-24.0)) <= 0.5 + 1e-9


@pytest.mark.parametrize("bad, match", [({"unlock_r": 0.2, "lock_r": 0.15}, "unlock_r"), ({"lock_steps": 0}, "lock_steps"),
                                        ({"unlock_steps": 1.5}, "unlock_steps"), ({"lock_r": float("nan")}, "lock_r"),
                                        ({"lock_steps": float("inf")}, "lock_steps"), ({"unlock_steps": "3"}, "unlock_steps"),
                                        ({"restart_memory": "yes"}, "restart_memory"),
                                        ({"settle_steps": -1}, "settle_steps"),
                                        ({"settle_rise": float("nan")}, "settle_rise")])
def test_bad_rule_names_the_value(bad, match):
    with pytest.raises(ValueError, match=match):
        HybridRule(**bad)


def test_deep_rl_controller_moves_angles_as_the_env_actions_do():
    steps = torch.tensor([2.0, 0.5], dtype=torch.float64)
    rl = DeepRL(lambda td: td.set("action", torch.arange(9)), ["alpha1", "alpha3"], steps.tolist())
    angles = torch.zeros(9, 4, dtype=torch.float64)
    command = rl.act(TensorDict(fields=torch.zeros(9, 4, 8), angles=torch.zeros(9, 4), batch_size=[9]), angles)
    deltas = action_to_deltas(torch.arange(9), steps)
    assert torch.equal(command[:, [0, 2]], deltas) and torch.equal(command[:, [1, 3]], angles[:, [1, 3]])


def test_deep_rl_turns_by_the_fine_steps_where_the_reward_read_reaches_the_level():
    rl = DeepRL(AlwaysIncrease(), ["alpha1"], [1.0], fine_steps_deg=[0.5], fine_from_r=0.15)
    angles = torch.zeros(3, 4, dtype=torch.float64)
    command = rl.act(_obs([0.1, 0.15, 0.2]), angles)  # searching, at the level, above it
    assert command[:, 0].tolist() == [1.0, 0.5, 0.5] and torch.equal(command[:, 1:], angles[:, 1:])
    with pytest.raises(ValueError, match="go together"):
        DeepRL(AlwaysIncrease(), ["alpha1"], [1.0], fine_steps_deg=[0.5])
    with pytest.raises(ValueError, match="fine_steps_deg needs one step per controlled angle"):
        DeepRL(AlwaysIncrease(), ["alpha1"], [1.0], fine_steps_deg=[0.5, 0.5], fine_from_r=0.15)


class Counter:
    """Scripted recurrent policy: its state counts the steps since is_init; action = the count mod 3."""

    in_keys = ["angles", "recurrent_state", "is_init"]

    def __call__(self, td):
        state = torch.where(td["is_init"][..., None], 0.0, td["recurrent_state"]) + 1
        td.set(("next", "recurrent_state"), state)
        self.count = state[:, 0, 0].clone()
        return td.set("action", state[:, 0, 0].long() % 3)


def test_deep_rl_carries_a_recurrent_policys_state_from_step_to_step():
    rl = DeepRL(Counter(), ["alpha1"], [1.0])
    # the plant's observation carries the state's shape (zeros: what the env's primer writes every step)
    obs = TensorDict(angles=torch.zeros(2, 4), recurrent_state=torch.zeros(2, 1, 5), batch_size=[2])
    angles = torch.zeros(2, 4, dtype=torch.float64)
    moves = [float(rl.act(obs, angles)[0, 0]) for _ in range(4)]
    assert moves == [0.0, 1.0, -1.0, 0.0]  # counts 1, 2, 3, 4: actions 1, 2, 0, 1
    rl.reset(obs, angles)
    assert float(rl.act(obs, angles)[0, 0]) == 0.0  # afresh: count 1
    rl.act(obs, angles)
    rl.restart(torch.tensor([False, True]))  # cavity 1 starts a new search at the next step
    rl.act(obs, angles)
    assert rl.policy.count.tolist() == [3.0, 1.0]


@pytest.mark.parametrize("restart_memory", [False, True])
def test_hybrid_restarts_a_recurrent_agents_memory_when_the_lock_is_lost_if_asked(restart_memory):
    rule = HybridRule(lock_r=0.15, lock_steps=1, unlock_r=0.1, unlock_steps=1, restart_memory=restart_memory)
    policy = Counter()
    hybrid = Hybrid(DeepRL(policy, ["alpha1"], [1.0]), ESCParams(), rule, ["alpha1"], 2)
    angles = torch.zeros(2, 4, dtype=torch.float64)

    def obs(r):
        return TensorDict(angles=torch.zeros(2, 4), recurrent_state=torch.zeros(2, 1, 5),
                          r=torch.tensor(r, dtype=torch.float32).reshape(2, 1), batch_size=[2])

    hybrid.reset(obs([0.0, 0.0]), angles)
    # cavity 0 locks at step 2 and loses the lock at step 3 (back to deep RL); cavity 1 never locks
    for r0 in [0.05, 0.2, 0.05, 0.05]:
        hybrid.act(obs([r0, 0.05]), angles)
    assert hybrid.mode.tolist() == [MODE_RL, MODE_RL] and hybrid.switches.tolist() == [2, 0]
    # the agent reads every step; restarted at the release (step 3), its count at step 4 is 2, else 4
    assert policy.count.tolist() == ([2.0, 4.0] if restart_memory else [4.0, 4.0])
