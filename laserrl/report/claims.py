"""The table of reproduction.md: each claim of the paper, the paper's number, laserrl's number,
the commands behind it and why the two differ.

Each row is built by a small function registered with ``@claim(key)`` from a
``ReportContext``; ``REQUIRED`` are the rows the report must always have.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from laserrl.analysis.landscape import interval_width, intervals
from laserrl.checkpoint import CheckpointError
from laserrl.model import load_model, record_dir
from laserrl.report.context import NOT_IN_ZOO, bank_paths

REQUIRED = ("r_modelocked", "r_planewave", "alpha1_starts", "alpha1_lock_range", "hysteresis", "hysteresis_width",
            "episodes_train", "episodes_finetune", "K_single", "K_bank")


@dataclass
class Claim:
    key: str
    claim: str  # what the paper claims
    paper: str  # the paper's number
    laserrl: str  # laserrl's number
    sources: list[str] = field(default_factory=list)  # labels of ctx.commands
    note: str = ""  # why the numbers differ


CLAIMS: dict[str, Callable] = {}


def claim(key: str):
    def register(fn):
        CLAIMS[key] = fn
        return fn
    return register


def _deg(iv: list[tuple[float, float]]) -> str:
    if not iv:
        return "none"
    return ", ".join(f"[{lo:g}, {hi:g}]" if lo != hi else f"{lo:g}" for lo, hi in iv) + " deg"


def _Ks(values: list[float], ok: list[bool]) -> str:
    iv = intervals(values, ok)
    if not iv:
        return "none"
    return ", ".join(f"[{lo:g}, {hi:g}]" if lo != hi else f"{lo:g}" for lo, hi in iv)


def _not_in_zoo(key: str, text: str, paper: str) -> Claim:
    return Claim(key, text, paper, NOT_IN_ZOO, [], "")


# ---------------------------------------------------------------------------------- bistability
@claim("r_modelocked")
def _r_modelocked(ctx) -> Claim:
    p = ctx.paths
    end = ", ".join(f"{a:g}" for a in p["agent"][-1].tolist())
    start = ", ".join(f"{a:g}" for a in p["start"])
    r = float(p["r_settled"][0])
    return Claim("r_modelocked",
                 f"Two controllers from (alpha1, alpha2) = ({start}) deg: the agent's path (i) ends mode-locked",
                 "r = 0.2062",
                 f"r = {r:.4f} at the end point ({end}) deg after {p['agent'].shape[0]} greedy steps "
                 f"(r = {float(p['r'][0, -1]):.4f} at the last step; r >= 0.15 first after {p['steps_to_lock']} steps)",
                 ["report", "duo"],
                 "The paper does not state its end point; here it is where the agent is after the duo protocol's "
                 f"{p['agent'].shape[0]} steps. The end state is settled there (<= "
                 f"{ctx.cfg['landscape']['settle_round_trips']} round trips), as the paper converges every step. "
                 + ("A mode-locked pulse, as in the paper" if r >= 0.15 else "Not mode-locked, unlike the paper")
                 + (f"; the pulse forms at ({_angles(p['agent'][p['steps_to_lock'] - 1])}) deg, step "
                    f"{p['steps_to_lock']} of the agent's path (fig. 4b)." if p["steps_to_lock"] else "."))


def _angles(row) -> str:
    return ", ".join(f"{a:g}" for a in row.tolist())


@claim("r_planewave")
def _r_planewave(ctx) -> Claim:
    p = ctx.paths
    r = float(p["r_settled"][1])
    plane = r < 0.05
    return Claim("r_planewave", "The straight path (ii) between the same start and end ends on a plane wave",
                 "r = 0.0066",
                 f"r = {r:.4f} (r = {float(p['r'][1, -1]):.4f} at the last step)", ["report", "duo"],
                 (f"A plane wave, as in the paper: r stays <= {float(p['r'][1].max()):.4f} at every step of the "
                  "straight path: no pulse forms along it (fig. 4b). "
                  "The r of a plane wave depends on the angles (fig. 4a), so with another end point the two numbers "
                  "need not agree closely.") if plane else
                 "Not a plane wave: in laserrl's cavity the straight path also reaches the mode-locked branch.")


@claim("alpha1_starts")
def _alpha1_starts(ctx) -> Claim:
    s = ctx.siso
    rows = s["protocol"]
    starts = [p["initial_angle_deg"] for p in rows]
    ok = [p["success"] for p in rows]
    res = s["result"]
    return Claim("alpha1_starts", "One controller (alpha1, K = 0.1): the agent mode-locks from every start alpha1 "
                 "in [-40, -10] deg", "all starts in [-40, -10] deg",
                 f"{sum(ok)} / {len(ok)} starts: {_deg(intervals(starts, ok))} (final r >= {res['success_r']:g} "
                 f"after {res['steps']} steps; mean final r {ctx.numbers['siso']['mean_final_reward']:.4f})",
                 ["report", "siso"], "")


@claim("alpha1_lock_range")
def _alpha1_lock_range(ctx) -> Claim:
    a = ctx.alpha1_sweep
    sw, cold = a["sweep"], a["cold"]
    r_min = float(ctx.siso["result"]["success_r"])
    parts = [f"swept up {_deg(sw.locked(r_min, 'up'))}", f"swept down {_deg(sw.locked(r_min, 'down'))}"]
    if cold is not None:
        parts.append(f"cold starts {_deg(intervals(sw.values_deg, cold >= r_min))}")
    best = int(sw.r_up[0].argmax())
    return Claim("alpha1_lock_range", f"alpha1 range where the laser is mode-locked (r >= {r_min:g}), "
                 "alpha2, alpha3, alpha_p fixed", "not stated (figs. 3, 4a: the agent ends near the best angle)",
                 "; ".join(parts) + f"; highest r {float(sw.r_up[0, best]):.4f} at {float(sw.values_deg[best]):g} deg",
                 ["report", "siso"],
                 f"On a {sw.step_deg:g} deg grid over {_deg([(float(sw.values_deg[0]), float(sw.values_deg[-1]))])}. "
                 "Which states exist depends on the history: the range differs between the sweeps.")


def _branch(sw, lo: float, hi: float) -> str:
    inside = (sw.values_deg >= lo) & (sw.values_deg <= hi)
    up, down = float(sw.r_up[0][inside].mean()), float(sw.r_down[0][inside].mean())
    return f"r {up:.3f} up / {down:.3f} down"


@claim("hysteresis")
def _hysteresis(ctx) -> Claim:
    sw = ctx.alpha1_sweep["sweep"]
    dr = float(ctx.cfg["landscape"]["hysteresis_dr"])
    iv = sw.hysteresis(dr)
    found = "yes: " + "; ".join(f"[{lo:g}, {hi:g}] deg ({_branch(sw, lo, hi)})" for lo, hi in iv) if iv else "no"
    return Claim("hysteresis", "Hysteresis (bistability) in alpha1: the state depends on the direction alpha1 is "
                 "turned, and the agent's alpha1 turns back while r rises", "yes (fig. 4a)",
                 f"{found}. {_detours(ctx)}", ["report", "siso"],
                 f"alpha1 swept up and down with the state carried over (one agent step per angle); listed where "
                 f"|r_up - r_down| > {dr:g}. The paper shows the hysteresis through the agent's path (fig. 4a); "
                 "fig. 4(a) here draws both.")


def _detours(ctx) -> str:
    """The agent's detours: starts from which alpha1 first overshoots its final angle by two or
    more steps and then comes back (the paper's hysteresis in the agent's path)."""
    rows = ctx.siso["protocol"]
    step = float(ctx.models["siso"].stage_cfg["steps_deg"][0])
    detour = []
    for p in rows:
        path = [p["initial_angle_deg"]] + [a[0] for a in p["angle_path_deg"]]
        final = path[-1]
        low, high = min(path), max(path)
        detour.append((final - low >= 2 * step and path[0] > final) or (high - final >= 2 * step and path[0] < final))
    starts = [p["initial_angle_deg"] for p in rows]
    if not any(detour):
        return "The agent goes straight to its final angle from every start."
    k = max(i for i, d in enumerate(detour) if d)
    p = rows[k]
    path = [p["initial_angle_deg"]] + [a[0] for a in p["angle_path_deg"]]
    turn = min(path) if path[0] > path[-1] else max(path)
    r = p["reward_path"]
    drop = max(max(r[:t + 1]) - r[t] for t in range(len(r)))  # largest fall below the best r so far
    return (f"The agent turns past its final angle and back from starts {_deg(intervals(starts, detour))}, e.g. "
            f"{path[0]:g} -> {turn:g} -> {path[-1]:g} deg, r falling by at most {drop:.4f} on the way "
            f"(final r {r[-1]:.4f}).")


@claim("hysteresis_width")
def _hysteresis_width(ctx) -> Claim:
    sw = ctx.alpha1_sweep["sweep"]
    iv = sw.hysteresis(float(ctx.cfg["landscape"]["hysteresis_dr"]))
    widths = [interval_width(i, sw.step_deg) for i in iv]
    return Claim("hysteresis_width", "Width of the hysteresis in alpha1", "not stated",
                 (", ".join(f"{w:g}" for w in widths) + " deg") if widths else "0 deg (none found)",
                 ["report", "siso"], f"Each interval counted in cells of the {sw.step_deg:g} deg grid (resolution "
                 f"+-{sw.step_deg:g} deg); a finer grid (report.landscape.alpha1_deg) narrows it down.")


# ---------------------------------------------------------------------------------- training
@claim("episodes_train")
def _episodes_train(ctx) -> Claim:
    rows = ctx.train_to_success
    m = ctx.models["siso"]
    trained = int(m.state["frames"]) / m.max_steps
    sources = ["siso"]
    parts = []
    reached = [r for r in rows if r["episodes"] is not None]
    for k, r in enumerate(rows):
        label = f"train_to_success:{k}"
        ctx.commands.setdefault(label, r["command"])
        sources.append(label)
    if reached:
        eps = [r["episodes"] for r in reached]
        parts.append(f"{sum(eps) / len(eps):.0f} episodes until the greedy success rate first reached {reached[0]['target']:g} "
                     f"(runs: {', '.join(f'{e:.0f}' for e in eps)}; {reached[0]['max_steps']}-step episodes)")
    missed = [r for r in rows if r["episodes"] is None]
    if missed:
        parts.append(f"{len(missed)} run(s) not within {', '.join(str(r['frames_trained'] // r['max_steps']) for r in missed)} episodes")
    parts.append(f"the siso model: trained {trained:.0f} episodes, success {ctx.siso['success_rate']:.2f}")
    cfg = m.config
    return Claim("episodes_train", "Episodes to train the single-input agent at K = 0.1", ">= 2000",
                 "; ".join(parts), sources,
                 f"An episode here is one cavity's run of {m.max_steps} agent steps (frames / max_steps; the paper "
                 f"trains with 40-step episodes). laserrl steps {cfg['env']['num_envs']} cavities at once, makes "
                 f"{cfg['optim']['updates_per_frame']:g} gradient steps per frame and ends a step after at most "
                 f"{cfg['env']['max_round_trips']} round trips, so an episode is not the paper's unit of work. "
                 "Success (>= 0.9 of the siso protocol's starts) is checked every train.eval_every_frames frames.")


@claim("episodes_finetune")
def _episodes_finetune(ctx) -> Claim:
    if not ctx.bank and not ctx.cfg["results"].get("transfer"):
        return _not_in_zoo("episodes_finetune", "Episodes to fine-tune the K = 0.1 agent to another K (transfer "
                           "learning)", "~300 on average")
    rows = ctx.transfer
    parts, sources = [], []
    for path in sorted({r["file"] for r in rows}):
        label = f"transfer:{len(sources)}"
        ctx.commands.setdefault(label, ctx.command_for(path))
        sources.append(label)
    done = [r for r in rows if r["episodes_to_success"] is not None]
    if rows:
        per_K = "; ".join(f"K = {r['K']:g}: " + (f"{r['episodes_to_success']:.0f}" if r["episodes_to_success"] is not None
                                                  else f"not within {r['episodes']:.0f}" if r["episodes"] is not None
                                                  else f"not within {r['frames']} frames") for r in rows)
        mean = (f"mean {sum(r['episodes_to_success'] for r in done) / len(done):.0f} episodes over the K that "
                f"succeeded" if done else "none succeeded")
        parts.append(f"to greedy success >= 0.9: {per_K} ({mean})")
    bank = []
    for path in bank_paths(ctx.bank):  # every model of an ensemble was fine-tuned on its own
        state = load_model(path)
        cfg = state["config"]
        if cfg.get("init_from"):
            run = record_dir(state["dir"])
            ev = json.loads((run / "eval.json").read_text()) if (run / "eval.json").exists() else {}
            bank.append((_K_text(cfg["stage"]["K"]), _finetune_episodes(state), ev.get("success_rate")))
    if bank:
        parts.append("bank models fine-tuned for " + "; ".join(
            f"K = {K}: {e:.0f} episodes" + (f" (success {s:.2f})" if s is not None else "") for K, e, s in bank))
        sources.append("bank")
    return Claim("episodes_finetune", "Episodes to fine-tune the K = 0.1 agent to another K (transfer learning)",
                 "~300 on average", "; ".join(parts) or "n/a (no transfer.json: report.results.transfer)", sources,
                 "Fine-tuning stops when the greedy success rate reaches 0.9, checked before training and every "
                 "train.eval_every_frames frames: where the K = 0.1 model already succeeds it needs 0 episodes. "
                 "Settings per K (transfer.by_K, e.g. longer episodes) apply to the fine-tuning and the scratch run "
                 "alike." + (f" {len(rows) - len(done)} of {len(rows)} runs did not reach 0.9 within their budget."
                             if len(done) < len(rows) else ""))


# ---------------------------------------------------------------------------------- generalisation
def _holding(by_K: dict) -> tuple[list[float], list[bool]]:
    """The K of an evaluation's ``by_K`` and whether each holds success >= 0.9."""
    return [float(k) for k in by_K], [v["success_rate"] >= 0.9 for v in by_K.values()]


def _rule(ctx, name: str) -> tuple[list[float], list[bool]]:
    return _holding(ctx.generalisation["rules"][name]["by_K"])


@claim("K_single")
def _K_single(ctx) -> Claim:
    if not ctx.has_generalisation:
        return _not_in_zoo("K_single", "One model trained at K = 0.1 controls the laser at other K",
                           "K from -0.2 to 0.4 except a few")
    g = ctx.generalisation
    ctx.commands.setdefault("generalisation", _generalisation_command(ctx))
    if "single" not in g["rules"]:
        value = "n/a (the bank evaluation was run without the single model: checkpoint=)"
    else:
        Ks, ok = _rule(ctx, "single")
        value = f"K in {_Ks(Ks, ok)} ({sum(ok)} / {len(ok)} grid points, success >= 0.9 of the starts)"
    return Claim("K_single", "One model trained at K = 0.1 controls the laser at other K",
                 "K from -0.2 to 0.4 except a few", value, ["generalisation"],
                 f"Grid K = {min(g['K']):g} .. {max(g['K']):g} ({len(g['K'])} values), {_protocol_text(ctx)}. "
                 + _far_locks(g))


def _protocol_text(ctx) -> str:
    """The protocol of the one model over K, in words."""
    m = ctx.models.get("k_base")
    if m is None:
        return "the protocol of the evaluation's stage"
    p, steps = m.stage_cfg.get("protocol") or {}, ctx.cfg["generalisation"].get("steps")
    what = (f"{p.get('repeats')} noise draws from ({', '.join(f'{a:g}' for a in m.base_deg)}) deg"
            if m.stage_cfg.get("init_fields") == "noise" else f"starts alpha1 {p.get('starts_deg')} deg")
    rule = (f"reach r >= {p.get('success_r')} and hold r >= {p['hold_r']}" if p.get("hold_r") is not None
            else f"final r >= {p.get('success_r')}")
    return f"the {len(m.stage_cfg['controlled'])}-controller model's protocol: {what}, {steps or p.get('steps')} greedy steps, {rule}"


@claim("K_bank")
def _K_bank(ctx) -> Claim:
    if not ctx.has_generalisation or "nearest" not in ctx.generalisation["rules"]:
        return _not_in_zoo("K_bank", "A bank of fine-tuned models covers the whole K range",
                           "all K in -0.2 .. 0.4 (4 models, K = -0.2, 0, 0.2, 0.4)")
    g = ctx.generalisation
    ctx.commands.setdefault("generalisation", _generalisation_command(ctx))
    parts = []
    for name, label in (("nearest", "nearest-K rule (knows K)"), ("max_q", "highest-Q rule (K unknown)"),
                        ("trial", "trial rule (K unknown)")):
        if name in g["rules"]:
            Ks, ok = _rule(ctx, name)
            parts.append(f"{label}: K in {_Ks(Ks, ok)} ({sum(ok)} / {len(ok)})")
    models = ", ".join(_K_text(k) for k in g.get("bank_K", []))
    failed = []
    if "nearest" in g["rules"]:
        Ks, ok = _rule(ctx, "nearest")
        failed = [K for K, good in zip(Ks, ok) if not good]
    return Claim("K_bank", "A bank of fine-tuned models covers the whole K range", "all K in -0.2 .. 0.4 "
                 "(4 models, K = -0.2, 0, 0.2, 0.4)", "; ".join(parts) + f" (models at K = {models})",
                 ["generalisation"],
                 "The paper does not say how the bank picks its model. A model given as a K range serves the K "
                 "inside it. "
                 + (f"The nearest-K rule fails at K = {', '.join(f'{K:g}' for K in failed)} (mean final r there: "
                    + ", ".join(f"{g['rules']['nearest']['by_K'][f'{K:g}']['mean_final_reward']:.3f}" for K in failed)
                    + "). " if failed else "")
                 + _max_q_note(g))


def _far_locks(g: dict) -> str:
    """Where the locks lie at the K where the one model fails and the bank's nearest model
    succeeds: the end angles of its successful rollouts against the starts."""
    single, nearest = g["rules"].get("single"), g["rules"].get("nearest")
    if single is None or nearest is None:
        return ""
    parts = []
    for K, at_K in nearest["by_K"].items():
        ends, starts = at_K.get("locked_end_deg"), at_K.get("starts_deg")
        if ends and starts and single["by_K"][K]["success_rate"] < 0.9 <= at_K["success_rate"]:
            parts.append(f"K = {K}: [{ends[0]:g}, {ends[1]:g}] deg")
            span = starts
    if not parts:
        return ""
    return ("Where the one model fails and the nearest bank model locks, that model ends at alpha1 in "
            + "; ".join(parts) + f" (starts in [{span[0]:g}, {span[1]:g}] deg).")


def _max_q_note(g: dict) -> str:
    if "max_q" not in g["rules"] or "nearest" not in g["rules"]:
        return ""
    share = {name: sum(v["success_rate"] >= 0.9 for v in g["rules"][name]["by_K"].values()) for name in ("max_q", "nearest")}
    if share["max_q"] >= share["nearest"]:
        return f"Highest-Q succeeds at as many K as nearest-K ({share['max_q']} / {len(g['K'])})."
    return (f"Highest-Q succeeds at fewer K ({share['max_q']} / {len(g['K'])}) than nearest-K ({share['nearest']}): "
            "the members' Q-values are trained separately and are not calibrated against each other.")


def _K_text(K) -> str:
    """A stage's K: one value, or a [lo, hi] range sampled at reset."""
    return f"[{K[0]:g}, {K[1]:g}]" if isinstance(K, (list, tuple)) else f"{float(K):g}"


def _finetune_episodes(state: dict, depth: int = 8) -> float:
    """Episodes of a fine-tuned model since its base: its own, plus those of the checkpoints it was
    fine-tuned from (a model fine-tuned again, e.g. over a K range, counts both). A parent counts
    only if it was itself warm-started on the same task (the same controlled angles): a base grown
    by the curriculum (two controllers, then four) is not a fine-tuning. A checkpoint that is gone
    ends the chain."""
    episodes = int(state["frames"]) / int(state["config"]["stage"]["max_steps"])
    parent = state["config"].get("init_from")
    if parent and depth > 0:
        try:
            parent_state = load_model(parent)
            grand = parent_state["config"].get("init_from")
            grand_state = load_model(grand) if grand else None
        except CheckpointError:
            return episodes
        task = list(parent_state["config"]["stage"]["controlled"])
        if grand_state is not None and list(grand_state["config"]["stage"]["controlled"]) == task:
            episodes += _finetune_episodes(parent_state, depth - 1)
    return episodes


def _generalisation_command(ctx) -> str:
    given = ctx.cfg["results"].get("generalisation")
    if given:
        return ctx.command_for(given)
    return ctx.commands["report"] + "  (evaluate_bank inside the report)"


# ---------------------------------------------------------------------------------- four controllers
@claim("miso")
def _miso(ctx) -> Claim:
    s = ctx.miso
    p, prot = s["per_start"], s["protocol"]
    r = p["reward_path"]
    lock = p["steps_to_lock"]
    after = min(r[lock - 1:]) if lock else None
    start = ", ".join(f"{a:g}" for a in p["initial_angles_deg"])
    sech = (f"sech start: r >= {s['result']['success_r']:g} after {lock} step(s), lowest r after that {after:.3f}, "
            f"final r {r[-1]:.3f}" if lock else f"sech start: no lock in {len(r)} steps (final r {r[-1]:.3f})")
    noise = (f"{prot['repeats']} noise draws: success {prot['success_rate']:.2f}, mean final r "
             f"{prot['mean_final_reward']:.3f}")
    return Claim("miso", f"Four controllers from ({start}) deg at K = {p['K']:g} drive the laser to mode-locking "
                 "and keep r near the optimum", "yes; r oscillates near the optimum (fig. 5)", f"{sech}; {noise}",
                 ["report", "miso"], "The miso stage starts from noise fields (stage protocol: lock, then hold "
                 "r >= 0.1 to the end); fig. 5 here and the first number use the paper's sech start.")


@claim("hybrid")
def _hybrid(ctx) -> Claim:
    c = ctx.control
    s = {n: r["summary"] for n, r in c["results"].items()}
    def cell(n):
        after = (s[n].get("locked_after_first_lock") or {}).get("mean")
        return (f"{n}: locked {s[n]['frac_locked']['mean']:.2f}" + (f" ({after:.2f} after its first lock)" if after is not None
                else "") + f", mean r {s[n]['mean_r']['mean']:.3f}")
    names = [n for n in ("hybrid", "rl", "esc") if n in s]
    controlled = c.get("controlled") or ["alpha1"]
    better = all(s["hybrid"]["frac_locked"]["mean"] >= s[n]["frac_locked"]["mean"]
                 and s["hybrid"]["mean_r"]["mean"] > s[n]["mean_r"]["mean"] for n in names if n != "hybrid")
    return Claim("hybrid", "Deep RL finds the lock, extremum seeking holds it while K drifts (hybrid, fig. 7)",
                 "shown qualitatively (no number)",
                 "; ".join(cell(n) for n in names) + f" ({c['num_cavities']} cavities, scenario {c['scenario'].get('name')}, "
                 f"locked: r >= {c['locked_r']:g})", ["control"],
                 ("The hybrid holds the lock at least as often as either part alone and with a higher mean r."
                  if better else "Here the hybrid does not beat both parts alone on both measures.") +
                 f" The controllers turn {', '.join(controlled)}"
                 + (" (the single-input model; the paper's hybrid turns all four plates)." if len(controlled) == 1 else ".")
                 + " docs/control.md has the comparison with the baselines.")


# ---------------------------------------------------------------------------------- beyond the paper
@claim("any_k")
def _any_k(ctx) -> Claim:
    text = "Beyond the paper: one agent for every K, from what instruments measure, told nothing about K"
    paper = "not in the paper (its agent reads the complex fields; other K need other models, picked by K)"
    if ctx.any_k is None:
        return Claim("any_k", text, paper, "not run: give report.checkpoints.any_k (zoo:miso-any-k)", [], "")
    Ks, ok = _holding(ctx.any_k["by_K"])
    ctx.commands.setdefault("any_k", ctx.models["any_k"].command or ctx.models["any_k"].path)
    ctx.commands.setdefault("generalisation", _generalisation_command(ctx))
    others = []
    for name, label in (("single", "the one K = 0.1 model (fields)"), ("nearest", "the bank told K"),
                        ("max_q", "the bank's highest-Q rule"), ("trial", "the bank's trial rule")):
        if name in ctx.generalisation["rules"]:
            _, good = _rule(ctx, name)
            others.append(f"{label} {sum(good)} / {len(good)}")
    card = ctx.models["any_k"].state["meta"].get("card") or {}
    env = ctx.models["any_k"].env_cfg
    return Claim("any_k", text, paper,
                 f"success >= 0.9 at K in {_Ks(Ks, ok)} ({sum(ok)} / {len(ok)} values; mean success "
                 f"{ctx.any_k['success_rate']:.2f}, mean steps to lock {ctx.any_k['mean_steps_to_lock'] or float('nan'):.1f})"
                 + (f"; on the same draws: {', '.join(others)}" if others else ""),
                 ["any_k", "generalisation"],
                 f"Observation {env.get('observation')}, "
                 + (f"a GRU of {env['gru_size']} units as memory" if env.get("gru_size")
                    else f"the last {env.get('history', 1)} readings stacked") + "; trained "
                 f"{card.get('frames_since_scratch') or card.get('frames')} frames through the curriculum "
                 f"({(card.get('train_seconds') or 0) / 60:.0f} min in its last stage). docs/measured.md has its "
                 "mismatched cavities and its control under drift.")


def build_claims(ctx) -> list[Claim]:
    return [fn(ctx) for fn in CLAIMS.values()]


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def markdown(ctx, rows: list[Claim], figures: dict[str, dict], out_dir: Path, meta: dict) -> str:
    """reproduction.md: how it was made, the claims table, the commands, the figures."""
    from laserrl.report.figures import FIGURES

    by_command: dict[str, str] = {}  # command -> label; sources with the same command share it
    labels = {}
    for row in rows:
        for s in row.sources:
            command = ctx.commands.get(s) or s
            labels[s] = by_command.setdefault(command, f"[{chr(ord('A') + len(by_command))}]")
    lines = ["# Reproduction of Sun, Kaiser, Brunton & Kutz (2020)", "",
             "Generated by `laserrl-report` (laserrl/conf/report.yaml); every number below is measured by the commands "
             "listed under the table. Regenerate with:", "", f"    {ctx.commands['report']}", "",
             f"Machine: {meta['machine']}; {meta['date']}. Wall time of the report: {meta['minutes']:.1f} min "
             f"(load average {meta['load']})"
             + (f", of which {meta['training_minutes']:.1f} min training the missing models with small budgets "
                f"(report.train; weaker than the paper's and docs/experiments.md numbers)"
                if meta.get("training_minutes") else "") + ".", "",
             "## Claims", "",
             "| claim of the paper | paper | laserrl | commands | differences explained |",
             "|---|---|---|---|---|"]
    for row in rows:
        refs = " ".join(dict.fromkeys(labels[s] for s in row.sources))
        lines.append(f"| {_cell(row.claim)} | {_cell(row.paper)} | {_cell(row.laserrl)} | {refs} | {_cell(row.note)} |")
    lines += ["", "Commands:", ""]
    for command, label in by_command.items():
        lines.append(f"- {label} `{command}`")
    sw = ctx.numbers.get("alpha1_sweep")
    lines += ["", "## How the landscapes and paths are computed", "",
              "- A landscape moves the angle one grid step per agent step with the cavity state carried over, "
              "with the numerics of the model's env (at most "
              + (f"{sw['max_round_trips']} round trips per step, tolerance {sw['tol']:g}" if sw else "the env's round trips per step")
              + "); each sweep starts from the sech fields settled at its first angle. A cold start settles the "
              "sech fields at each angle on its own.",
              "- Every step runs at least "
              + (f"{sw['min_round_trips']}" if sw else "the env's minimum of")
              + " round trips: J1 (alpha1) is the last, unitary element of the round trip, so the first round "
              "trip after turning alpha1 alone leaves |u|^2 + |v|^2 unchanged and a stopping test after it "
              "would show the old angle (laserrl/envs/step.py).",
              "- Physics of each model's env, as saved in its model (landscapes use the siso model's for "
              "fig. 4a and the duo model's for fig. 4b): " + "; ".join(_physics_line(m) for m in ctx.models.values()) + ".",
              "- The agents' paths are replayed through the physics with the env's exact semantics (largest "
              "difference of r to the greedy rollout: "
              + ", ".join(f"{k} {v:.1e}" for k, v in ctx.numbers.get("replay_max_abs_dr", {}).items()) + ").", ""]
    lines += ["## Figures", ""]
    for name, done in figures.items():
        fig = FIGURES[name]
        lines.append(f"### {fig.paper}: {name}")
        lines.append("")
        if "skipped" in done:
            lines.append(f"Not drawn: {done['skipped']}")
        else:
            rel = Path(done["path"]).resolve().relative_to(out_dir.resolve())
            lines.append(f"![{fig.paper}]({rel.as_posix()})")
            lines.append("")
            lines.append(fig.caption)
        lines.append("")
    return "\n".join(lines)


def _physics_line(model) -> str:
    from laserrl.envs.factory import make_params, make_task

    p, task = make_params(model.env_cfg), make_task(model.env_cfg, model.stage_cfg)
    return (f"{model.role}: n = {p.n}, {p.integrator} z_steps = {p.z_steps}, {task.min_round_trips} to "
            f"{task.max_round_trips} round trips per step, tol {task.tol:g}, {task.dtype}")


def to_json(rows: list[Claim]) -> list[dict]:
    return [asdict(r) for r in rows]


__all__ = ["CLAIMS", "Claim", "REQUIRED", "build_claims", "claim", "markdown", "to_json"]
