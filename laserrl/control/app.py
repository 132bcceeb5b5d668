"""``laserrl-control controller=... scenario=...``: hold cavities mode-locked while K drifts and jumps.

Runs one controller (or ``controller=all``: every controller on the same cavities, the
comparison table) for ``scenario.steps`` agent steps on ``num_cavities`` cavities, each
with its own K trajectory and start angles from the scenario and ``seed``. Every
controller gets the same budget: one setting of the angles per agent step, each step the
same round trips as the DQN's training env (the checkpoint's ``env`` config; without a
checkpoint, ``laserrl/conf/env``). Writes ``control.json`` (metrics per controller, averaged over
cavities with spread, and the traces) and ``control.png`` (r, K and the angles over time,
the paper's fig. 7) into the run directory, and prints the table.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from laserrl.model import load_model
from laserrl.config import ConfigError, _number
from laserrl.control.baselines import Genetic, GeneticParams, HillClimb, HillClimbParams, RandomSearch, RandomSearchParams
from laserrl.control.esc import ESCParams, ExtremumSeeking, observed_r
from laserrl.control.hybrid import DeepRL, Hybrid, HybridRule
from laserrl.control.metrics import held_by_K0, locked_by_K, per_cavity, summarise
from laserrl.control.plant import CavityPlant, Plates
from laserrl.control.scenarios import Scenario
from laserrl.physics.checks import CAVITY_KEYS
from laserrl.envs.laser_env import ANGLE_NAMES

#: ``controller=all`` runs these, in this order
ALL = ("random_search", "hill_climb", "ga", "esc", "rl", "hybrid")
NEEDS_CHECKPOINT = ("rl", "hybrid")
METRICS = ("frac_locked", "mean_r", "first_lock_step", "locked_after_first_lock", "recovery_steps", "round_trips")


def _params(cls, cfg: Mapping[str, Any], where: str):
    """Dataclass ``cls`` from a controller config (without ``name``); errors name the config."""
    kwargs = {k: v for k, v in cfg.items() if k != "name"}
    try:
        return cls(**kwargs)
    except ValueError as err:
        raise ConfigError(f"{where}: {err}") from None
    except TypeError as err:
        raise ConfigError(f"{where}: {err}") from None


def build_controller(name: str, ccfg: Mapping[str, Any], controlled, num_cavities: int, seed: int, rl_policy=None,
                     rl_steps_deg=None, where: str = "controller", rl_fine=None):
    """The controller ``name`` from its config; ``rl_policy`` (greedy TensorDict policy) for rl/hybrid,
    whose plates turn by ``rl_steps_deg`` per step, or with ``rl_fine`` = (steps, r) by those steps where
    the reward read is >= r (``DeepRL``)."""
    if name in NEEDS_CHECKPOINT and rl_policy is None:
        raise ConfigError(f"controller {name} needs a DQN: give checkpoint=MODEL (zoo:NAME or a laserrl-train run directory)")
    try:
        if name == "esc":
            return ExtremumSeeking(_params(ESCParams, ccfg, where), controlled, num_cavities)
        if name == "random_search":
            return RandomSearch(_params(RandomSearchParams, ccfg, where), controlled, num_cavities, seed)
        if name == "hill_climb":
            return HillClimb(_params(HillClimbParams, ccfg, where), controlled, num_cavities, seed)
        if name == "ga":
            return Genetic(_params(GeneticParams, ccfg, where), controlled, num_cavities, seed)
        if name == "rl":
            return DeepRL(rl_policy, controlled, rl_steps_deg, *(rl_fine or (None, None)))
        if name == "hybrid":
            rule = _params(HybridRule, {k: v for k, v in ccfg.items() if k != "esc"}, where)
            esc = _params(ESCParams, ccfg["esc"], f"{where}.esc")
            try:
                esc.resolve(controlled)
            except ValueError as err:
                raise ConfigError(f"{where}.esc: {err}") from None
            return Hybrid(DeepRL(rl_policy, controlled, rl_steps_deg, *(rl_fine or (None, None))), esc, rule, controlled,
                          num_cavities)
    except ValueError as err:
        if isinstance(err, ConfigError):
            raise
        raise ConfigError(f"{where}: {err}") from None
    raise ConfigError(f"unknown controller {name!r}; choose from {list(ALL) + ['all']}")


def run_controllers(controllers: Mapping[str, Any], plant: CavityPlant, K: np.ndarray, init_angles_deg: np.ndarray,
                    progress: bool = False) -> dict:
    """Run every controller on its own B cavities of one plant (B x len(controllers) cavities,
    stepped together: one batched physics call per round trip for all of them).

    K (B, T) and the start angles (B, 4) deg are the same for every controller. Returns per
    controller the traces as numpy arrays: ``r`` (B, T) after each step, ``angles`` (B, T, 4)
    deg applied in each step, ``round_trips`` (B, T), ``mode`` (B, T) of a hybrid (0 deep RL,
    1 ESC) or None, and ``r_read`` (B, T): with measured observations, the instruments' reward
    r_measured the controllers read after each step (``observed_r``), else None (they read ``r``).
    """
    B, T = K.shape
    n = len(controllers)
    if plant.num_cavities != B * n:
        raise ValueError(f"the plant has {plant.num_cavities} cavities; {n} controllers x {B} cavities needed")
    Kt = torch.as_tensor(np.tile(K, (n, 1)), dtype=torch.float64)
    obs = plant.reset(torch.as_tensor(np.tile(init_angles_deg, (n, 1)), dtype=torch.float64), Kt[:, 0])
    part = {name: slice(i * B, (i + 1) * B) for i, name in enumerate(controllers)}
    angles_now = plant.angles_deg
    for name, c in controllers.items():
        c.reset(obs[part[name]], angles_now[part[name]])
    r = np.zeros((B * n, T))
    angles = np.zeros((B * n, T, 4))
    round_trips = np.zeros((B * n, T), dtype=np.int64)
    r_read = np.zeros((B * n, T)) if "r_measured" in obs.keys() else None
    mode = {name: np.zeros((B, T), dtype=np.int64) for name, c in controllers.items() if hasattr(c, "mode")}
    for t in range(T):
        plant.set_K(Kt[:, t])
        angles_now = plant.angles_deg
        # the simulated K beside the observation, for the one controller that is told K (bank_rule=nearest)
        seen = obs.clone(recurse=False).set("K", Kt[:, t, None].to(torch.float32))
        command = torch.cat([c.act(seen[part[name]], angles_now[part[name]]) for name, c in controllers.items()])
        for name in mode:
            mode[name][:, t] = controllers[name].mode.cpu().numpy()
        obs = plant.step(command)
        r[:, t] = plant.r.cpu().numpy()
        if r_read is not None:
            r_read[:, t] = observed_r(obs)
        angles[:, t] = plant.true_angles_deg.cpu().numpy()  # where the plates are
        round_trips[:, t] = obs["round_trips"].reshape(-1).cpu().numpy()
        if progress and ((t + 1) % max(1, T // 10) == 0 or t + 1 == T):
            means = ", ".join(f"{name} {r[part[name], : t + 1].mean():.3f}" for name in controllers)
            print(f"step {t + 1}/{T}: mean r {means}", flush=True)
    return {name: {"r": r[part[name]], "angles": angles[part[name]], "round_trips": round_trips[part[name]],
                   "mode": mode.get(name), "r_read": None if r_read is None else r_read[part[name]]}
            for name in controllers}


def _check(cfg: DictConfig) -> None:
    _number(cfg, "num_cavities", low=1, integer=True)
    _number(cfg, "seed", integer=True)
    _number(cfg, "locked_r", low=0)
    _number(cfg, "success_r", low=0)
    _number(cfg, "hold_steps", low=1, integer=True)
    if cfg.threads is not None:
        _number(cfg, "threads", low=1, integer=True)
    if cfg.get("rl_fine_from_r") is not None:
        _number(cfg, "rl_fine_from_r", low=0)
    if cfg.metric not in METRICS:
        raise ConfigError(f"metric must be one of {list(METRICS)}, got {cfg.metric!r}")
    if cfg.controller.get("name") == "all":
        names = _all_names(cfg.controller)
        if len(names) > 1 and cfg.metric_controller not in names:
            raise ConfigError(f"metric_controller must be one of the controllers run {names}, got {cfg.metric_controller!r}")
    if cfg.controlled is not None:
        names = list(cfg.controlled)
        if not _distinct_of(names, ANGLE_NAMES):
            raise ConfigError(f"controlled must name 1 to 4 distinct angles of {ANGLE_NAMES}, got {names!r}")


def _rl_steps(value, count: int) -> list[float]:
    """``rl_steps_deg``: the plate turn per action step of deep RL (alone and in the hybrid), a number
    for every controlled angle or one per angle, each finite and > 0."""
    values = [value] * count if isinstance(value, (int, float)) and not isinstance(value, bool) else value
    if not isinstance(values, (list, tuple)) or len(values) != count or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0 for v in values):
        raise ConfigError(f"rl_steps_deg must be a number > 0 or a list of {count} numbers > 0 (one per controlled "
                          f"angle), got {value!r}")
    return [float(v) for v in values]


def _rl_step_rule(cfg: DictConfig, stage: Mapping[str, Any]) -> tuple[list[float], tuple[list[float], float] | None]:
    """Deep RL's plate turns: (steps, fine) with fine = (fine steps, reward level) or None. By default the
    checkpoint's own: its stage's ``steps_deg``, and where it was trained with finer steps near a lock, its
    ``fine_steps_deg`` from ``fine_from``. ``rl_steps_deg`` replaces the steps; ``rl_fine_from_r`` turns by
    the checkpoint's fine steps (its ``fine_steps_deg``, or else its ``steps_deg``) from that level on."""
    own = [float(s) for s in stage["steps_deg"]]
    own_fine = None if stage.get("fine_from") is None else ([float(s) for s in stage["fine_steps_deg"]],
                                                            float(stage["fine_from"]))
    steps = own if cfg.get("rl_steps_deg") is None else _rl_steps(cfg.rl_steps_deg, len(own))
    if cfg.get("rl_fine_from_r") is None:
        return steps, own_fine
    if own_fine is None and cfg.get("rl_steps_deg") is None:
        raise ConfigError("rl_fine_from_r turns the plates by the checkpoint's own steps near a lock and by "
                          "rl_steps_deg elsewhere: give rl_steps_deg too")
    return steps, (own if own_fine is None else own_fine[0], float(cfg.rl_fine_from_r))


def _distinct_of(names: list, allowed) -> bool:
    """Whether ``names`` is a non-empty list of distinct members of ``allowed``."""
    return bool(names) and len(set(names)) == len(names) and all(n in allowed for n in names)


def _all_names(ccfg) -> list[str]:
    """The controllers ``controller=all`` runs: ``controller.only`` (some of them) or every one."""
    only = ccfg.get("only")
    if only is None:
        return list(ALL)
    names = [only] if isinstance(only, str) else list(only)
    if not _distinct_of(names, ALL):
        raise ConfigError(f"controller.only must list distinct controllers of {list(ALL)}, got {names!r}")
    return names


def _rounded(x: np.ndarray, digits: int = 5) -> list:
    return np.round(x, digits).tolist()


def run_control(cfg: DictConfig) -> dict:
    """The app without Hydra's main (tests call it with a composed config); returns control.json."""
    _check(cfg)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    container = OmegaConf.to_container(cfg, resolve=True)
    scfg = container["scenario"]
    try:
        scenario = Scenario(**scfg)
    except TypeError as err:
        raise ConfigError(f"scenario: {err}") from None
    ccfg = container["controller"]
    names = _all_names(ccfg) if ccfg.get("name") == "all" else [ccfg.get("name")]
    configs = {n: ccfg[n] for n in names} if ccfg.get("name") == "all" else {names[0]: ccfg}
    where = {n: (f"controller.{n}" if ccfg.get("name") == "all" else "controller") for n in names}

    state, policy_for, steps_deg, rl_fine = None, None, None, None
    env_cfg = dict(container["env"])
    controlled = container["controlled"]
    if cfg.checkpoint and cfg.get("bank"):
        raise ConfigError("give checkpoint=MODEL (one model) or bank=[MODEL, ...] (a bank), not both")
    if cfg.get("bank"):
        state, policy_for = bank_policy(container)
    elif cfg.checkpoint:
        from laserrl.evaluate import load_agent

        state = load_model(cfg.checkpoint)
        policy_for = lambda plant: load_agent(state, plant.env.action_spec_unbatched)  # noqa: E731
    if state is not None:
        stage = state["config"]["stage"]
        env_cfg = dict(state["config"]["env"])  # the per-step physics the DQN was trained with
        rl_controlled = list(stage["controlled"])
        if controlled is not None and any(n in NEEDS_CHECKPOINT for n in names) and list(controlled) != rl_controlled:
            raise ConfigError(f"controlled={list(controlled)} differs from the angles the checkpoint's DQN controls "
                              f"{rl_controlled}; leave controlled unset to use those")
        controlled = controlled or rl_controlled
        steps_deg, rl_fine = _rl_step_rule(cfg, stage)
    elif any(n in NEEDS_CHECKPOINT for n in names):
        raise ConfigError(f"controller {'all' if len(names) > 1 else names[0]} needs a DQN: give checkpoint=MODEL "
                          "(zoo:NAME or a laserrl-train run directory) or bank=[MODEL, ...]")
    controlled = list(controlled or ["alpha1"])
    if cfg.compile is not None:
        env_cfg["compile"] = bool(cfg.compile)
    B, seed = int(cfg.num_cavities), int(cfg.seed)
    plates = _params(Plates, container.get("plates") or {}, "plates")
    K, init_angles = scenario.sample(B, seed)
    # every controller on its own copy of the B cavities, all in one plant
    try:
        plant = CavityPlant(env_cfg, controlled, B * len(names), scenario.steps, seed=seed, init_fields=scenario.init_fields,
                            device=cfg.device, plates=plates, physics_spread=container.get("physics_spread"), copies=len(names))
    except ValueError as err:
        if "physics_spread" in str(err):
            raise ConfigError(str(err)) from None
        raise
    # a policy of its own for each controller: a bank's trial rule keeps per-cavity state
    controllers = {n: build_controller(n, configs[n], controlled, B, seed,
                                       policy_for(plant) if policy_for and n in NEEDS_CHECKPOINT else None,
                                       steps_deg, where[n], rl_fine) for n in names}

    t0 = time.perf_counter()
    traces_np = run_controllers(controllers, plant, K, init_angles, progress=bool(cfg.progress))
    seconds = time.perf_counter() - t0
    results, traces = {}, {}
    idx = [ANGLE_NAMES.index(a) for a in controlled]
    for n in names:
        trace = traces_np[n]
        cav = per_cavity(trace["r"], trace["round_trips"], scenario.jumps["times"], float(cfg.locked_r), int(cfg.hold_steps),
                         float(cfg.success_r))
        results[n] = {"summary": summarise(cav, len(scenario.jumps["times"])), "per_cavity": cav}
        if isinstance(scenario.K0, list):  # a grid of K: success per K, as laserrl-eval's
            results[n]["summary"]["held_to_end_by_K0"] = held_by_K0(cav, scenario.K0)
        if np.ptp(K, axis=1).max() > 0:  # K moves: where the time unlocked after the first lock is lost
            results[n]["summary"]["after_first_lock_by_K"] = locked_by_K(trace["r"], K, cav["first_lock_step"],
                                                                         float(cfg.locked_r))
        traces[n] = {"r": _rounded(trace["r"]), "angles_deg": _rounded(trace["angles"][:, :, idx], 3)}
        if trace["r_read"] is not None:  # measured observations: what the controllers read
            traces[n]["r_read"] = _rounded(trace["r_read"])
        if trace["mode"] is not None:
            traces[n]["mode"] = trace["mode"].tolist()
            results[n]["summary"]["frac_esc"] = float((trace["mode"] == 1).mean())
        print(f"{n}: {_row(n, results[n]['summary'])}", flush=True)

    out = {
        "controllers": names, "controller_settings": configs,  # each controller's settings as run (e.g. the hybrid's lock_r)
        "scenario": {**scfg, "jump_times": scenario.jumps["times"]},
        "num_cavities": B, "seed": seed, "controlled": controlled, "rl_steps_deg": steps_deg,
        "rl_fine": None if rl_fine is None else {"steps_deg": rl_fine[0], "from_r": rl_fine[1]}, "locked_r": float(cfg.locked_r),
        "success_r": float(cfg.success_r),
        "hold_steps": int(cfg.hold_steps), "checkpoint": state["path"] if state and not cfg.get("bank") else None,
        **({"bank": state["bank"], "bank_rule": cfg.bank_rule} if cfg.get("bank") else {}),
        "plates": {"noise_deg": plates.noise_deg, "backlash_deg": plates.backlash_deg},
        "physics_spread": container.get("physics_spread"),
        **({} if plant.cavities is None else {"cavities": [dict(zip(CAVITY_KEYS, map(float, row)))
                                                           for row in plant.cavities[:B].double().cpu()]}),
        "env": {k: env_cfg[k] for k in ("max_round_trips", "tol", "dtype") if k in env_cfg} | {"physics": env_cfg.get("physics")},
        "seconds": round(seconds, 1), "results": results, "K": _rounded(K), "init_angles_deg": _rounded(init_angles, 3), "traces": traces,
    }
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / "control.json"
    path.write_text(json.dumps(out))
    table = comparison_table(out)
    (run_dir / "control.md").write_text(table + "\n")
    if cfg.plots:
        from laserrl.plots import plot_control

        plot_control(out, run_dir / "control.png", cavity=int(cfg.plot_cavity))
    print(table)
    print(f"{B} cavities x {len(names)} controller(s) x {scenario.steps} steps in {seconds:.0f} s")
    print(f"control: {path}")
    return out


def bank_policy(container: Mapping[str, Any]):
    """``bank=[MODEL, ...]``: (the first member's model, whose env and stage set the physics and the
    actions, with ``bank`` the members' paths; a factory of the bank's greedy policy for a plant).
    ``bank_rule``: ``trial`` (K unknown, ``TrialBank`` with ``bank_trial``) or ``nearest`` (told K)."""
    from laserrl.agents.bank import make_nearest_actor, make_trial_actor
    from laserrl.evaluate import member_qnet, bank_paths, load_bank

    rule = container.get("bank_rule")
    if rule not in ("trial", "nearest"):
        raise ConfigError(f"bank_rule must be trial (K unknown) or nearest (told K), got {rule!r}")
    if not isinstance(container["bank"], list):
        raise ConfigError(f"bank must be a list of models, got {container['bank']!r}")
    members, model_K, trial = load_bank(container["bank"], container.get("bank_trial"))
    stages = {(m[0]["config"]["stage"]["name"], tuple(m[0]["config"]["stage"]["controlled"])) for m in members}
    if len(stages) != 1:
        raise ConfigError(f"bank: the models are trained for different tasks {sorted(stages)}; give models of one task")

    def policy_for(plant):
        spec = plant.env.action_spec_unbatched
        qnets = [member_qnet(m, spec) for m in members]
        return make_trial_actor(qnets, spec, trial) if rule == "trial" else make_nearest_actor(qnets, model_K, spec)

    first = members[0][0]
    return {**first, "bank": bank_paths(members)}, policy_for


def _fmt(s: dict, digits: int = 3, pct: bool = False) -> str:
    if s["mean"] is None:
        return "-"
    if pct:
        return f"{100 * s['mean']:.0f} % ± {100 * s['std']:.0f}"
    return f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"


def _row(name: str, s: dict) -> str:
    return (f"locked {_fmt(s['frac_locked'], pct=True)}, mean r {_fmt(s['mean_r'])}, "
            f"first lock {_fmt(s['first_lock_step'], 1)} steps, recovery {_fmt(s['recovery_steps'], 1)} steps")


def comparison_table(out: dict) -> str:
    """Markdown table of the summaries (mean ± standard deviation over cavities)."""
    lines = ["| controller | time locked (r >= %g) | after the first lock | held to the end | mean r | "
             "steps to first lock (locked) | recovery after a jump, steps (recovered) | round trips |" % out["locked_r"],
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for n in out["controllers"]:
        s = out["results"][n]["summary"]
        rec = "-" if s["recovered"] is None else f"{_fmt(s['recovery_steps'], 1)} ({100 * s['recovered']:.0f} %)"
        held = "-" if s.get("held_to_end") is None else f"{100 * s['held_to_end']:.0f} %"
        lines.append(f"| {n} | {_fmt(s['frac_locked'], pct=True)} | {_fmt(s['locked_after_first_lock'], pct=True)} | "
                     f"{held} | {_fmt(s['mean_r'])} | "
                     f"{_fmt(s['first_lock_step'], 1)} ({100 * s['locked_ever']:.0f} %) | {rec} | "
                     f"{s['round_trips']['mean']:.0f} |")
    by_K = {n: out["results"][n]["summary"].get("held_to_end_by_K0") for n in out["controllers"]}
    if all(by_K.values()):  # scenario.K0 a list: reach r >= success_r and hold r >= locked_r to the end, per K
        Ks = list(next(iter(by_K.values())))
        lines += ["", "Held to the end (reach r >= %g, then r >= %g at every step), per K0:" % (
            out.get("success_r", float("nan")), out["locked_r"]), "",
                  "| controller | " + " | ".join(Ks) + " | K with >= 90 % |", "|---|" + "---:|" * (len(Ks) + 1)]
        for n, rates in by_K.items():
            lines.append(f"| {n} | " + " | ".join(f"{rates[k]:.2f}" for k in Ks) +
                         f" | {sum(v >= 0.9 for v in rates.values())} of {len(Ks)} |")
    bands = {n: out["results"][n]["summary"].get("after_first_lock_by_K") for n in out["controllers"]}
    if all(bands.values()):  # K moves within the run
        lines += ["", "After the first lock, per band of K: time locked (r >= %g), %% (the band's share of the time "
                  "unlocked, %%):" % out["locked_r"], ""]
        edges = sorted({tuple(b["K"]) for v in bands.values() for b in v})
        lines += ["| controller | " + " | ".join(f"K in [{lo:g}, {hi:g})" for lo, hi in edges) + " |",
                  "|---|" + "---:|" * len(edges)]
        for n, v in bands.items():
            by = {tuple(b["K"]): b for b in v}
            lines.append(f"| {n} | " + " | ".join(
                f"{100 * by[e]['locked']:.0f} ({100 * by[e]['share_of_unlocked']:.0f})" if e in by else "-"
                for e in edges) + " |")
    return "\n".join(lines)


def sweep_metric(out: dict, cfg: DictConfig) -> float:
    """What ``main`` returns (for sweepers): the mean over cavities of ``cfg.metric`` for the
    controller run, or with ``controller=all`` for ``cfg.metric_controller``; NaN if undefined."""
    names = out["controllers"]
    name = cfg.metric_controller if len(names) > 1 else names[0]
    value = out["results"][name]["summary"][cfg.metric]["mean"]
    return float(value) if value is not None else float("nan")
