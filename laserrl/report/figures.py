"""The report's figures: a registry of small functions, one per figure of the paper.

Each entry draws one PNG from a ``ReportContext`` (which computes what it asks for, once)
or raises ``FigureSkipped`` with the reason. To add a figure, decorate a function
``draw(ctx, path)`` with ``@figure(name, paper_figure, caption)``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from laserrl.envs.laser_env import ANGLE_NAMES  # noqa: E402
from laserrl.physics import sech_fields  # noqa: E402
from laserrl.plots import plot_generalisation, plot_training  # noqa: E402

DPI = 90  # keeps each PNG well under 300 kB


class FigureSkipped(Exception):
    """A figure that cannot be drawn with what this report has; the message says why."""


@dataclass(frozen=True)
class Figure:
    name: str  # file name without .png
    paper: str  # the paper's figure, e.g. "fig. 4"
    caption: str
    draw: Callable  # draw(ctx, path) -> None


FIGURES: dict[str, Figure] = {}


def figure(name: str, paper: str, caption: str):
    """Register ``draw(ctx, path)`` as the figure ``name`` (drawn in registration order)."""
    def register(draw):
        FIGURES[name] = Figure(name, paper, caption, draw)
        return draw
    return register


def _save(fig, path: Path) -> None:
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def _centring_shift(u: torch.Tensor, v: torch.Tensor) -> int:
    """Roll that puts the peak of |u|^2 + |v|^2 in the middle of the (periodic) time window."""
    n = u.shape[-1]
    return n // 2 - int((u.abs().square() + v.abs().square()).argmax())


def _field_map(ax, params, u_path: torch.Tensor, title: str, shift: int = 0) -> None:
    """|field| (steps x t) as an image; row 0 is the initial field; rolled by ``shift`` samples."""
    t = params.time_grid()
    amp = torch.roll(u_path.abs().double(), shift, -1).numpy()
    im = ax.imshow(amp, aspect="auto", origin="lower", interpolation="nearest", cmap="magma",
                   extent=[float(t[0]), float(t[-1]), -0.5, amp.shape[0] - 0.5])
    ax.set(xlabel="t (centred on the final peak)" if shift else "t", ylabel="step", title=title)
    plt.colorbar(im, ax=ax, pad=0.01)


def _with_initial(replay, i: int, params) -> tuple[torch.Tensor, torch.Tensor]:
    """Fields of replayed path ``i`` after each step, with the sech fields of the reset in front."""
    u0, v0 = sech_fields(1, params, dtype=replay.u_path.dtype)
    return torch.cat([u0, replay.u_path[i]]), torch.cat([v0, replay.v_path[i]])


# ------------------------------------------------------------------------------------------ fig. 2
@figure("fig2_training", "fig. 2", "Training of the single-input agent: final reward of finished episodes, "
        "TD loss and exploration rate against frames (the siso model's run history).")
def fig2_training(ctx, path: Path) -> None:
    if not ctx.history:
        raise FigureSkipped(f"fig. 2 needs history.json next to the siso checkpoint ({ctx.models['siso'].run_dir})")
    plot_training(ctx.history, path)


# ------------------------------------------------------------------------------------------ fig. 3
@figure("fig3_siso", "fig. 3", "Single-input control (alpha1, K of the siso stage): reward per step from every "
        "start alpha1 of the protocol; (i)-(iii) the detailed starts: reward and alpha1 per step, |u| and |v| after "
        "each step (row 0: the sech fields of the reset).")
def fig3_siso(ctx, path: Path) -> None:
    s = ctx.siso
    rows, details, replay, params = s["protocol"], s["details"], s["replay"], s["params"]
    fig = plt.figure(figsize=(13, 3 * len(details) + 0.5))
    gs = fig.add_gridspec(len(details), 4, width_ratios=[1.3, 1, 1, 1])
    ax = fig.add_subplot(gs[:, 0])
    cmap = plt.get_cmap("viridis")
    starts = [p["initial_angle_deg"] for p in rows]
    lo, hi = min(starts), max(starts)
    for p in rows:
        c = cmap((p["initial_angle_deg"] - lo) / max(hi - lo, 1e-9))
        ax.plot(range(1, len(p["reward_path"]) + 1), p["reward_path"], color=c, lw=1)
    ax.axhline(s["result"]["success_r"], color="k", ls="--", lw=0.8)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(lo, hi))
    fig.colorbar(sm, ax=ax, label="start alpha1 (deg)")
    ax.set(xlabel="step", ylabel="r", title=f"reward per start (success {s['success_rate']:.0%})")
    for i, p in enumerate(details):
        label = "(" + "i" * (i + 1) + ")" if i < 3 else f"({i + 1})"
        a = fig.add_subplot(gs[i, 1])
        steps = range(1, len(p["reward_path"]) + 1)
        a.plot(steps, p["reward_path"], "C0.-", ms=3)
        a.set(xlabel="step", ylabel="r", title=f"{label} start alpha1 = {p['initial_angle_deg']:g} deg")
        b = a.twinx()
        b.plot(steps, [q[0] for q in p["angle_path_deg"]], "C1.-", ms=3)
        b.set_ylabel("alpha1 (deg)", color="C1")
        u, v = _with_initial(replay, i, params)
        shift = _centring_shift(u[-1], v[-1])
        _field_map(fig.add_subplot(gs[i, 2]), params, u, f"{label} |u|", shift)
        _field_map(fig.add_subplot(gs[i, 3]), params, v, f"{label} |v|", shift)
    fig.tight_layout()
    _save(fig, path)


# ------------------------------------------------------------------------------------------ fig. 4
def _shade(ax, intervals, step, **kw) -> None:
    for k, (lo, hi) in enumerate(intervals):
        ax.axvspan(lo - step / 2, hi + step / 2, color="0.85", zorder=0, label=kw.get("label") if k == 0 else None)


def _map_panel(ax, ctx, which: str) -> None:
    m, p = ctx.alpha_map, ctx.paths
    sw = m["sweep"]
    r = sw.r_up if which == "up" else sw.r_down
    a1, a2 = sw.values_deg.numpy(), m["alpha2"].numpy()
    mesh = ax.pcolormesh(a1, a2, r.numpy(), shading="nearest", cmap="viridis", vmin=0, vmax=float(max(sw.r_up.max(), sw.r_down.max())))
    plt.colorbar(mesh, ax=ax, label="r", pad=0.01)
    bistable = ((sw.r_up - sw.r_down).abs() > float(ctx.cfg["landscape"]["hysteresis_dr"])).double().numpy()
    if bistable.any():
        ax.contour(a1, a2, bistable, levels=[0.5], colors="w", linewidths=0.8, linestyles=":")
    start = p["start"]
    for key, style, label in (("agent", "w.-", "(i) agent"), ("straight", "r.--", "(ii) straight")):
        xy = torch.cat([torch.tensor([start], dtype=torch.float64), p[key]])
        ax.plot(xy[:, 0], xy[:, 1], style, ms=3, lw=1.2, label=label)
    ax.plot(*start, "ko", ms=6, mfc="none")
    ax.plot(*p["agent"][-1].tolist(), "k*", ms=9)
    ax.set(xlabel="alpha1 (deg)", ylabel="alpha2 (deg)", title=f"(b) r, alpha1 swept {which}")
    ax.legend(fontsize=7, loc="lower left")


def _fields_panel(ax, ctx, i: int) -> None:
    p = ctx.paths
    t = p["params"].time_grid().numpy()
    shift = _centring_shift(p["u"][i], p["v"][i])
    ax.plot(t, torch.roll(p["u"][i].abs().double(), shift, -1).numpy(), label="|u|")
    ax.plot(t, torch.roll(p["v"][i].abs().double(), shift, -1).numpy(), "--", label="|v|")
    name = "(i) agent" if i == 0 else "(ii) straight"
    ax.set(xlabel="t (centred on the peak; the window is periodic)", ylabel="amplitude",
           title=f"(c) {name}: end state r = {float(p['r_settled'][i]):.4f}\n(at the last step {float(p['r'][i, -1]):.4f})")
    ax.legend(fontsize=8)


@figure("fig4_bistability", "fig. 4", "Bistability. (a) r against alpha1 reached sweeping alpha1 up and down with "
        "the cavity state carried over (one agent step per angle), and from cold starts; grey: the sweeps disagree "
        "(hysteresis); lines: the single-input agent's paths from the detailed starts. (b) r over alpha1 x alpha2 "
        "(the duo model's stage) swept up and down in alpha1 on each alpha2 row (dotted: where the sweeps disagree), "
        "with the duo agent's greedy path (i) and the straight path (ii) between the same start (circle) and end "
        "(star) in as many steps. (c) |u| and |v| at the end of "
        "each path, settled at the end point.")
def fig4_bistability(ctx, path: Path) -> None:
    a = ctx.alpha1_sweep
    sw, cold = a["sweep"], a["cold"]
    dr = float(ctx.cfg["landscape"]["hysteresis_dr"])
    fig = plt.figure(figsize=(15, 8.5))
    gs = fig.add_gridspec(2, 3)
    ax = fig.add_subplot(gs[0, :2])
    x = sw.values_deg.numpy()
    _shade(ax, sw.hysteresis(dr), sw.step_deg, label=f"|r_up - r_down| > {dr:g}")
    ax.plot(x, sw.r_up[0].numpy(), "^-", color="C0", ms=4, label="alpha1 swept up")
    ax.plot(x, sw.r_down[0].numpy(), "v-", color="C3", ms=4, label="alpha1 swept down")
    if cold is not None:
        ax.plot(x, cold.numpy(), "o", color="0.5", ms=3, mfc="none", label="cold start at each angle")
    for k, p in enumerate(ctx.siso["details"]):
        xs = [q[0] for q in p["angle_path_deg"]]
        ax.plot(xs, p["reward_path"], ".-", color=f"C{k + 4}", lw=0.9, ms=3,
                label=f"agent from alpha1 = {p['initial_angle_deg']:g}")
        ax.plot(xs[-1], p["reward_path"][-1], "*", color=f"C{k + 4}", ms=9)
    base = sw.base_deg[0].tolist()
    ax.set(xlabel="alpha1 (deg)", ylabel="r", title=f"(a) alpha1 landscape at alpha2, alpha3, alpha_p = "
           f"{base[1]:g}, {base[2]:g}, {base[3]:g} deg, K = {sw.K:g}")
    ax.legend(fontsize=7, ncol=2)
    _map_panel(fig.add_subplot(gs[1, 0]), ctx, "up")
    _map_panel(fig.add_subplot(gs[1, 1]), ctx, "down")
    _fields_panel(fig.add_subplot(gs[0, 2]), ctx, 0)
    _fields_panel(fig.add_subplot(gs[1, 2]), ctx, 1)
    fig.tight_layout()
    _save(fig, path)


# ------------------------------------------------------------------------------------------ fig. 5
@figure("fig5_miso", "fig. 5", "Four controllers from the miso stage's start (paper: 15, -5, 20, 84 deg, K = 0) "
        "with sech initial fields, greedy: reward and the four angles per step, |u| and |v| after each step.")
def fig5_miso(ctx, path: Path) -> None:
    s = ctx.miso
    p, replay, params = s["per_start"], s["replay"], s["params"]
    fig, axes = plt.subplots(2, 2, figsize=(13, 7.5))
    steps = range(1, len(p["reward_path"]) + 1)
    axes[0, 0].plot(steps, p["reward_path"], ".-", ms=3)
    axes[0, 0].axhline(s["result"]["success_r"], color="k", ls="--", lw=0.8)
    start = ", ".join(f"{a:g}" for a in p["initial_angles_deg"])
    axes[0, 0].set(xlabel="step", ylabel="r", title=f"reward from ({start}) deg, K = {p['K']:g}")
    controlled = list(ctx.models["miso"].stage_cfg["controlled"])
    for k, name in enumerate(controlled):
        axes[0, 1].plot(steps, [q[k] - p["initial_angles_deg"][ANGLE_NAMES.index(name)] for q in p["angle_path_deg"]],
                        label=name)
    axes[0, 1].set(xlabel="step", ylabel="angle - start (deg)", title="angles")
    axes[0, 1].legend(fontsize=8)
    u, v = _with_initial(replay, 0, params)
    shift = _centring_shift(u[-1], v[-1])
    _field_map(axes[1, 0], params, u, "|u|", shift)
    _field_map(axes[1, 1], params, v, "|v|", shift)
    fig.tight_layout()
    _save(fig, path)


# ------------------------------------------------------------------------------------------ fig. 6
@figure("fig6_generalisation", "fig. 6", "Generalisation across K: success rate at each K of the grid of one model "
        "(trained at K = 0.1) and, where a bank is given, of its rules (nearest K, which knows K; highest Q and trial, "
        "which do not).")
def fig6_generalisation(ctx, path: Path) -> None:
    if not ctx.has_generalisation:
        from laserrl.report.context import NOT_IN_ZOO

        raise FigureSkipped(NOT_IN_ZOO)
    plot_generalisation(ctx.generalisation, path)


# ------------------------------------------------------------------------------------------ fig. 7
@figure("fig7_hybrid", "fig. 7", "Hybrid control while K drifts and jumps: deep RL finds the lock, extremum "
        "seeking holds it; r, K and the angles over time, next to ESC alone, deep RL alone and the baselines.")
def fig7_hybrid(ctx, path: Path) -> None:
    """From ``report.results.control`` (a laserrl-control control.json), else a small
    ``laserrl-control`` run here with the k_base model (``report.control``)."""
    from laserrl.plots import plot_control

    plot_control(ctx.control, path, dpi=DPI)


# ------------------------------------------------------------------------------- beyond the paper
@figure("any_k_comparison", "beyond the paper", "One agent for every K from measured signals (experiment=miso_any_k, "
        "told nothing about K) against the paper's answers on the same K values and noise draws: the one model "
        "trained at K = 0.1 and, where a bank is given, its rules (nearest K, which knows K; highest Q and trial, "
        "which do not). Success rate per K of the four-controller protocol.")
def any_k_comparison(ctx, path: Path) -> None:
    from laserrl.results import summary

    if ctx.any_k is None:
        raise FigureSkipped("no K-blind agent: give report.checkpoints.any_k (a model of experiment=miso_any_k)")
    g = ctx.generalisation
    plot_generalisation({**g, "rules": {**g["rules"], "any_k": summary(ctx.any_k)}}, path)


def draw_figures(ctx, out_dir: Path, names: list[str] | None = None) -> dict[str, dict]:
    """Draw the registered figures (or ``names``) into ``out_dir``; returns name -> {path | skipped}."""
    from laserrl.config import ConfigError

    unknown = sorted(set(names or []) - set(FIGURES))
    if unknown:
        raise ConfigError(f"report.figures: unknown figure(s) {unknown}; figures: {list(FIGURES)}")
    out_dir.mkdir(parents=True, exist_ok=True)
    done: dict[str, dict] = {}
    for name, fig in FIGURES.items():
        if names and name not in names:
            continue
        path = out_dir / f"{name}.png"
        try:
            fig.draw(ctx, path)
        except FigureSkipped as why:
            print(f"report: {name} skipped: {why}")
            done[name] = {"skipped": str(why)}
            continue
        print(f"report: {path}")
        done[name] = {"path": str(path)}
    return done


__all__ = ["FIGURES", "Figure", "FigureSkipped", "draw_figures", "figure"]
