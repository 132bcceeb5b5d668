"""``laserrl-eval checkpoint=PATH``: the paper's inference protocol with a trained agent.

Greedy rollouts of ``eval.steps`` (20) agent steps from every initial angle in
``eval.starts_deg`` (alpha1 in {-40, -38, ..., -10} deg), sech initial fields, at
each K in ``eval.K`` (the checkpoint's K unless given). Success for one start:
final r >= ``eval.success_r`` (0.18), or, with ``eval.hold_r`` set, r reaches
``success_r`` and never falls below ``hold_r`` afterwards. ``eval.repeats`` runs each start
several times with its own initial noise. Writes ``eval.json`` (and a plot) into the run
directory and prints its path.

    laserrl-eval checkpoint=zoo:siso                      # a model shipped with laserrl (laserrl-zoo list)
    laserrl-eval checkpoint=outputs/2026-11-22/10-00-00   # a run directory (its model/)
    laserrl-eval checkpoint=RUN_DIR eval.K=0.2           # any K
    laserrl-eval checkpoint=RUN_DIR 'eval.K=[0,0.1,0.2]'  # several K at once
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Mapping

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tensordict import TensorDict

from laserrl.agents.bank import nearest_model
from laserrl.agents.dqn import build_qnet, make_actor
from laserrl.checkpoint import CheckpointError
from laserrl.model import ensemble_members, load_model
from laserrl.envs.actions import hold_action
from laserrl.envs.factory import make_env, min_round_trips
from laserrl.envs.laser_env import ANGLE_NAMES, base_env_of, reset_at
from laserrl.results import failure_line, failure_modes, grid_success, summary
from laserrl.validate import ConfigError, check_number, check_numbers, check_one_of

def load_qnet(state: Mapping[str, Any], action_spec):
    """Rebuild the Q-network of a checkpoint for an env with ``action_spec`` (the mean of its
    members' Q-values for an ensemble, ``MeanQ``)."""
    cfg = state["config"]
    net = cfg["agent"]["network"]
    n_env = int(action_spec.n)
    if int(state["num_actions"]) != n_env:
        raise CheckpointError(
            f"checkpoint {state.get('path')} has a {state['num_actions']}-action head (stage {state.get('stage')}); "
            f"this task needs {n_env} actions"
        )
    qnets = []
    for weights in ensemble_members(state):  # one, or the members of an ensemble
        qnet = build_qnet(n_env, cfg["env"], net)
        try:
            qnet.load_state_dict(weights)
        except RuntimeError as err:
            raise CheckpointError(f"checkpoint {state.get('path')} does not match its network config: "
                                  f"{str(err).splitlines()[0]}") from None
        qnets.append(qnet.eval())
    if len(qnets) == 1:
        return qnets[0]
    from laserrl.agents.bank import MeanQ

    return MeanQ(qnets).eval()


def load_agent(state: Mapping[str, Any], action_spec):
    """Rebuild the greedy actor of a checkpoint for an env with ``action_spec``."""
    return make_actor(load_qnet(state, action_spec), action_spec)


def _as_list(x) -> list[float]:
    if x is None:
        return []
    if isinstance(x, (int, float)):
        return [float(x)]
    return [float(v) for v in x]


def success_mask(r: torch.Tensor, success_r: float, hold_r: float | None, held_steps: int | None = None) -> torch.Tensor:
    """Success per rollout from rewards r (B, steps).

    hold_r None: final r >= success_r (the paper's single-input protocol).
    Otherwise: r reaches success_r at some step and stays >= hold_r at every later step
    (the four-controller bar: lock, then keep the lock for the rest of the episode). With
    ``held_steps`` the lock must also come early enough to be held for at least that many of the
    last steps, so that a policy sweeping through a lock just before the end does not count.
    """
    if hold_r is None:
        return r[:, -1] >= success_r
    reached = r >= success_r  # (B, T)
    if held_steps:  # a lock at step index t is held for the T - t steps t ... T - 1
        reached[:, max(0, r.shape[-1] - int(held_steps) + 1):] = False
    # broken[t]: some step after t falls below hold_r
    below = (r < hold_r).flip(-1).cumsum(-1).flip(-1)  # number of steps >= t below hold_r
    later_below = torch.cat([below[:, 1:], torch.zeros_like(below[:, :1])], -1) > 0
    return (reached & ~later_below).any(-1)


def success_rate(success: torch.Tensor) -> float:
    """The fraction of rollouts that succeeded, exact for counts (9 of 10 is 0.9, which a float32
    mean is not: 0.89999998 would miss train.stop_at_success=0.9)."""
    return int(success.sum()) / success.numel()


def _stage_base_angles(stage_cfg: Mapping[str, Any]) -> list[float]:
    base = []
    for name in ANGLE_NAMES:
        v = stage_cfg["init_angles_deg"][name]
        base.append(float(v) if isinstance(v, (int, float)) else 0.5 * (float(v[0]) + float(v[1])))
    return base


def with_protocol(eval_cfg: Mapping[str, Any], protocol: Mapping[str, Any] | None) -> dict:
    """The ``eval`` config with its null values taken from the stage's ``protocol``."""
    return {**dict(protocol or {}), **{k: v for k, v in dict(eval_cfg).items() if v is not None}}


def check_eval_config(eval_cfg: Mapping[str, Any], protocol: Mapping[str, Any] | None = None) -> None:
    """The ``eval`` config's own values (a null takes the stage's ``protocol`` or the training env's);
    a bad one raises a ConfigError naming ``eval.KEY``."""
    for key in ("steps", "repeats", "max_round_trips", "min_round_trips"):
        check_number(eval_cfg.get(key), f"eval.{key}", low=1, integer=True, optional=True)
    check_number(eval_cfg.get("seed"), "eval.seed", low=0, high=2**32 - 1, integer=True, optional=True)
    for key in ("success_r", "hold_r"):
        check_number(eval_cfg.get(key), f"eval.{key}", optional=True)
    if eval_cfg.get("held_steps") is not None:
        check_number(eval_cfg["held_steps"], "eval.held_steps", low=1, integer=True)
        effective = with_protocol(eval_cfg, protocol)
        if effective.get("hold_r") is None:
            raise ConfigError("eval.held_steps needs eval.hold_r (a lock held to the end; the four-controller protocol)")
        if effective.get("steps") is not None and int(eval_cfg["held_steps"]) > int(effective["steps"]):
            raise ConfigError(f"eval.held_steps ({eval_cfg['held_steps']}) exceeds eval.steps ({effective['steps']})")
    for key in ("K", "starts_deg"):
        check_numbers(eval_cfg.get(key), f"eval.{key}", optional=True, scalar_ok=True)
    if eval_cfg.get("init_fields") is not None:
        check_one_of(eval_cfg["init_fields"], "eval.init_fields", ("sech", "noise"))
    check_number(eval_cfg.get("physics_spread"), "eval.physics_spread", low=0, high=0.5, optional=True)


def evaluate_policy(policy_for_env, env_cfg: Mapping[str, Any], stage_cfg: Mapping[str, Any],
                    eval_cfg: Mapping[str, Any], seed: int = 0) -> dict:
    """Greedy rollouts of the evaluation protocol; returns the eval.json content.

    ``policy_for_env(env)`` returns the TensorDict policy to roll out (it gets the env so
    that it can read the action spec). Every combination of K in ``eval.K`` (the stage's K
    if empty), first-controlled-angle start in ``eval.starts_deg`` (the stage's start if
    empty) and ``eval.repeats`` copies runs as one batch; with noise initial fields each
    copy draws its own noise from the env's seeded generator, seeded by ``eval.seed`` (if
    set) or ``seed``.
    """
    if eval_cfg.get("seed") is not None:
        seed = int(eval_cfg["seed"])
    # eval.* values left null take the stage's own protocol
    eval_cfg = with_protocol(eval_cfg, stage_cfg.get("protocol"))
    for key in ("steps", "success_r"):
        if eval_cfg.get(key) is None:
            raise ConfigError(f"eval.{key} is not set and stage {stage_cfg.get('name')!r} has no protocol.{key}")
    env_cfg = dict(env_cfg)
    for key in ("max_round_trips", "min_round_trips"):
        if eval_cfg.get(key):
            env_cfg[key] = int(eval_cfg[key])
    if eval_cfg.get("dtype"):
        env_cfg["dtype"] = eval_cfg["dtype"]
    env_cfg["compile"] = bool(eval_cfg.get("compile", env_cfg.get("compile", False)))
    check_eval_config(eval_cfg)
    # the nominal cavity of the model (or eval.physics), or with eval.physics_spread every rollout its own
    # cavity, D, E0, tau, g0, Gamma each drawn within +-spread of it (drawn after the noise fields: the same
    # noise draws as on the nominal cavity)
    spread = eval_cfg.get("physics_spread")
    env_cfg["physics_spread"] = None if spread is None else float(spread)
    mismatch = {k: v for k, v in dict(eval_cfg.get("physics") or {}).items() if v is not None}
    if mismatch:  # a cavity other than the one trained on (laserrl-eval env.physics.g0=...)
        env_cfg["physics"] = {**dict(env_cfg.get("physics") or {}), **mismatch}
    steps = int(eval_cfg["steps"])
    repeats = int(eval_cfg.get("repeats") or 1)
    threshold = float(eval_cfg["success_r"])
    hold_r = eval_cfg.get("hold_r")
    hold_r = None if hold_r is None else float(hold_r)
    held_steps = None if eval_cfg.get("held_steps") is None else int(eval_cfg["held_steps"])
    Ks = _as_list(eval_cfg.get("K"))
    if not Ks:
        K_stage = stage_cfg["K"]
        Ks = [float(K_stage)] if isinstance(K_stage, (int, float)) else [0.5 * (float(K_stage[0]) + float(K_stage[1]))]
    first = stage_cfg["controlled"][0]
    base = _stage_base_angles(stage_cfg)
    starts = _as_list(eval_cfg.get("starts_deg")) or [base[ANGLE_NAMES.index(first)]]
    combos = [(K, s, rep) for K in Ks for s in starts for rep in range(repeats)]
    B = len(combos)
    # K stays at each value of the grid (a drift of the training stage is off; laserrl-control drives K over time)
    env = make_env(env_cfg, stage_cfg, B, seed, centred=False, max_steps=steps, K_drift=0.0, K_jump=0.0,
                   init_fields=eval_cfg.get("init_fields") or stage_cfg.get("init_fields", "sech"))
    policy = policy_for_env(env)
    init = torch.tensor([base] * B, dtype=torch.float64)
    init[:, ANGLE_NAMES.index(first)] = torch.tensor([s for _, s, _ in combos], dtype=torch.float64)
    reset_td = TensorDict(init_angles=torch.deg2rad(init), init_K=torch.tensor([K for K, _, _ in combos], dtype=torch.float64),
                          batch_size=[B])
    td = reset_at(env, reset_td)
    cavities = _cavities(env)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(steps, policy, auto_reset=False, tensordict=td)
    r = rollout["next", "r"].squeeze(-1)  # (B, steps)
    angles = torch.rad2deg(rollout["next", "angles"][..., -4:].double())  # (B, steps, 4): the newest of a history
    ctrl = [ANGLE_NAMES.index(n) for n in stage_cfg["controlled"]]
    success = success_mask(r, threshold, hold_r, held_steps)
    per_start = []
    for i, (K, s, rep) in enumerate(combos):
        locked = (r[i] >= threshold).nonzero().flatten()
        per_start.append({
            "K": K, "initial_angle_deg": s, "angle": first, "repeat": rep,
            "initial_angles_deg": init[i].tolist(),
            "final_reward": float(r[i, -1]), "success": bool(success[i]),
            "steps_to_lock": int(locked[0]) + 1 if locked.numel() else None,
            "reward_path": [float(x) for x in r[i]],
            "angle_path_deg": [[float(a) for a in angles[i, t, ctrl]] for t in range(steps)],
        })
        if cavities is not None:
            per_start[-1]["cavity"] = cavities[i]
        if "model" in rollout.keys():
            per_start[-1]["model_path"] = [int(m) for m in rollout["model"][i]]
    final = r[:, -1]
    locks = [p["steps_to_lock"] for p in per_start if p["success"] and p["steps_to_lock"] is not None]
    by_K = {}
    for K in Ks:
        rows = [p for p in per_start if p["K"] == K]
        # where the successful rollouts ended, in the first controlled angle (the starts are in starts_deg)
        ends = [p["angle_path_deg"][-1][0] for p in rows if p["success"]]
        by_K[f"{K:g}"] = {"success_rate": sum(p["success"] for p in rows) / len(rows),
                          "mean_final_reward": sum(p["final_reward"] for p in rows) / len(rows),
                          "locked_end_deg": [min(ends), max(ends)] if ends else None,
                          "starts_deg": [min(starts), max(starts)]}
    result = {
        "stage": stage_cfg.get("name"), "steps": steps, "success_r": threshold, "hold_r": hold_r,
        "held_steps": held_steps, "repeats": repeats, "seed": int(seed), "max_round_trips": env_cfg["max_round_trips"],
        "min_round_trips": min_round_trips(env_cfg), "K": Ks, "physics_changed": mismatch,
        "physics_spread": env_cfg["physics_spread"],
        "success_rate": success_rate(success), "mean_final_reward": float(final.mean()),
        "mean_steps_to_lock": (sum(locks) / len(locks)) if locks else None,
        "by_K": by_K, "per_start": per_start,
    }
    if "action_value" in rollout.keys():  # a Q-network's policy: does it value holding still once locked?
        result["hold_value_gap"] = hold_value_gap(rollout["action_value"], r, threshold, len(ctrl))
    return {**result, "failures": failure_modes(result)}


def hold_value_gap(action_value: torch.Tensor, r: torch.Tensor, success_r: float, num_controlled: int) -> dict:
    """How far below its best action a Q-network values the all-hold action (no plate moves):
    the median of max_a Q - Q(hold) over the steps taken from a lock (r >= ``success_r`` after
    the step before) and over the other steps. ``action_value`` (B, T, actions), r (B, T)."""
    hold = hold_action(num_controlled)
    gap = (action_value.max(-1).values - action_value[..., hold]).double()
    from_lock = torch.zeros_like(r, dtype=torch.bool)
    from_lock[:, 1:] = r[:, :-1] >= success_r
    med = lambda x: float(x.median()) if x.numel() else None  # noqa: E731
    return {"from_lock": med(gap[from_lock]), "searching": med(gap[~from_lock])}


def _cavities(env) -> list[dict] | None:
    """Each rollout's D, E0, tau, g0, Gamma where the env drew them (``physics_spread``), else None."""
    cavity = getattr(base_env_of(env).state, "cavity", None)
    if cavity is None:
        return None
    from laserrl.physics.checks import CAVITY_KEYS

    return [dict(zip(CAVITY_KEYS, map(float, row))) for row in cavity.double().cpu()]


def write_eval(result: dict, out_dir: str | Path, plots: bool = True, kind: str = "rewards") -> Path:
    """Write eval.json and its figure: per-start rewards (``eval_rewards.png``), or success
    against K for a bank (``kind="generalisation"``, ``generalisation.png``)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "eval.json"
    path.write_text(json.dumps(result, indent=1))
    if plots:
        from laserrl.plots import plot_eval, plot_generalisation

        if kind == "generalisation":
            plot_generalisation(result, out_dir / "generalisation.png")
        else:
            plot_eval(result, out_dir / "eval_rewards.png")
    print(f"eval: {path}")
    return path


def evaluate_checkpoint(checkpoint: str, eval_cfg: Mapping[str, Any], out_dir: str | Path, stage: Mapping | None = None) -> dict:
    """Run the protocol for one checkpoint; returns and writes the eval.json content."""
    state = load_model(checkpoint)
    cfg = state["config"]
    stage_cfg = dict(stage) if stage is not None else dict(cfg["stage"])
    result = evaluate_policy(lambda env: load_agent(state, env.action_spec_unbatched), cfg["env"], stage_cfg, eval_cfg,
                             int(cfg.get("seed", 0)))
    result = {"checkpoint": state["path"], **result}
    write_eval(result, out_dir, eval_cfg.get("plots", True))
    print(f"success {result['success_rate']:.2f}; {failure_line(result['failures'])}")
    gap = result.get("hold_value_gap")
    if gap and None not in gap.values():
        print(f"Q of the best action above the all-hold action's, median: {gap['from_lock']:.3g} on steps from a lock, "
              f"{gap['searching']:.3g} on the others")
    return result


def _stage_K(state: Mapping[str, Any]) -> float | tuple[float, float]:
    """The K a checkpoint was trained at: a number, or (lo, hi) for a K range sampled at reset."""
    K = state["config"]["stage"]["K"]
    if isinstance(K, (int, float)):
        return float(K)
    if isinstance(K, (list, tuple)) and len(K) == 2 and all(isinstance(k, (int, float)) for k in K):
        return (float(min(K)), float(max(K)))
    raise CheckpointError(f"checkpoint {state.get('path')} has stage.K = {K!r}; a bank needs a number or a [lo, hi] range")


def _load_member(entry, index: int) -> list[dict]:
    """The checkpoints of one bank entry: a path, or a list of paths (an ensemble, ``MeanQ``)
    whose models were trained at the same K."""
    paths = [entry] if isinstance(entry, (str, Path)) else list(entry)
    if not paths or not all(isinstance(p, (str, Path)) for p in paths):
        raise ConfigError(f"bank[{index}]: give a checkpoint path or a list of paths (an ensemble), got {entry!r}")
    states = [load_model(p) for p in paths]
    Ks = [_stage_K(st) for st in states]
    if any(k != Ks[0] for k in Ks):
        raise ConfigError(f"bank[{index}]: the models of an ensemble must be trained at the same K, got "
                          + ", ".join(f"{st['path']}: {k}" for st, k in zip(states, Ks)))
    return states


def load_bank(bank: list, trial: Mapping[str, Any] | None):
    """A bank's members (each a list of models: one, or an ensemble's), their training K
    (``_stage_K``) and the trial rule of ``bank_trial`` (``TrialRule``); errors name
    ``bank[i]`` or ``bank_trial``."""
    from laserrl.agents.bank import TrialRule

    try:
        rule = TrialRule(**dict(trial or {}))
    except TypeError as err:
        raise ConfigError(f"bank_trial: {err}; its keys are steps, min_rise, lock_r") from None
    members = [_load_member(entry, i) for i, entry in enumerate(bank)]
    return members, [_stage_K(m[0]) for m in members], rule


def bank_paths(members: list[list[dict]]) -> list:
    """The members' paths as given: a path, or a list of an ensemble's paths."""
    return [m[0]["path"] if len(m) == 1 else [st["path"] for st in m] for m in members]


def member_qnet(states: list[dict], action_spec):
    """The Q-network of a bank member: the model itself, or the mean of an ensemble's."""
    from laserrl.agents.bank import MeanQ

    qnets = [load_qnet(st, action_spec) for st in states]
    return qnets[0] if len(qnets) == 1 else MeanQ(qnets)


def evaluate_bank(bank: list, eval_cfg: Mapping[str, Any], out_dir: str | Path, stage: Mapping | None = None,
                  single: str | None = None, trial: Mapping[str, Any] | None = None) -> dict:
    """Generalisation across K of a bank of models (and optionally one model), the paper's fig. 6.

    ``bank``: one entry per member, a checkpoint path or a list of paths trained at the same K
    (an ensemble whose Q-values are averaged, ``laserrl.agents.bank.MeanQ``).
    Rules: ``nearest`` acts at each K with the model trained at the nearest K (an oracle
    that knows K; a model fine-tuned over a K range serves the K inside it, see
    ``nearest_model``); ``max_q`` acts with ``MaxQBank`` and ``trial`` with ``TrialBank``
    (``trial``: the ``TrialRule``'s settings), neither told K; ``single`` is the one model
    ``single`` at every K. Writes eval.json with the success rate per K of each rule and
    ``generalisation.png``.
    """
    from laserrl.agents.bank import make_bank_actor, make_trial_actor

    members, model_K, rule = load_bank(bank, trial)
    cfg = members[0][0]["config"]
    stage_cfg = dict(stage) if stage is not None else dict(cfg["stage"])
    check_eval_config(eval_cfg, stage_cfg.get("protocol"))  # before eval.seed is read
    # the draws: eval.seed, else the first member's training seed
    seed = int(eval_cfg["seed"]) if eval_cfg.get("seed") is not None else int(cfg.get("seed", 0))
    Ks = _as_list(eval_cfg.get("K"))
    if not Ks:
        raise ConfigError("a bank evaluation needs the K grid: eval.K=[-0.2,-0.15,...,0.4]")
    rules: dict[str, dict] = {}
    rules["max_q"] = summary(evaluate_policy(
        lambda env: make_bank_actor([member_qnet(m, env.action_spec_unbatched) for m in members], env.action_spec_unbatched),
        cfg["env"], stage_cfg, eval_cfg, seed))
    rules["trial"] = summary(evaluate_policy(
        lambda env: make_trial_actor([member_qnet(m, env.action_spec_unbatched) for m in members],
                                     env.action_spec_unbatched, rule),
        cfg["env"], stage_cfg, eval_cfg, seed))
    nearest_by_K: dict[str, dict] = {}
    for m, member in enumerate(members):
        mine = [K for K in Ks if nearest_model(model_K, K) == m]
        if mine:
            res = evaluate_policy(lambda env, mm=member: make_actor(member_qnet(mm, env.action_spec_unbatched),
                                                                    env.action_spec_unbatched),
                                  cfg["env"], stage_cfg, {**dict(eval_cfg), "K": mine}, seed)
            nearest_by_K.update({k: {**v, "model": m} for k, v in res["by_K"].items()})
    nearest_by_K = {f"{K:g}": nearest_by_K[f"{K:g}"] for K in Ks}
    rules["nearest"] = {"success_rate": sum(v["success_rate"] for v in nearest_by_K.values()) / len(Ks),
                        "mean_final_reward": sum(v["mean_final_reward"] for v in nearest_by_K.values()) / len(Ks),
                        "by_K": nearest_by_K}
    if single:
        state = load_model(single)
        rules["single"] = summary(evaluate_policy(lambda env: load_agent(state, env.action_spec_unbatched),
                                                   cfg["env"], stage_cfg, eval_cfg, seed))
    result = {"bank": bank_paths(members),
              "bank_K": [k if isinstance(k, float) else list(k) for k in model_K], "single": single, "K": Ks,
              "stage": stage_cfg.get("name"), "seed": seed,
              "trial_rule": dataclasses.asdict(rule), "rules": rules,
              "grid_success": grid_success(rules, len(Ks))}
    write_eval(result, out_dir, eval_cfg.get("plots", True), kind="generalisation")
    return result
