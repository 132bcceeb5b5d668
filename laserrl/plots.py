"""Figures next to a run: training curves (paper fig. 2) and per-start reward
trajectories with angle paths (paper fig. 3); and success per K of several evaluations side by side:

    python -m laserrl.plots over-k OUT.png --panel "fields" --curve "one model=RUN/eval.json#single" ...
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot_training(history: list[dict], path: str | Path) -> Path:
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    ep = [(h["frames"], h["train/episode_final_r"]) for h in history if "train/episode_final_r" in h]
    if ep:
        axes[0].plot(*zip(*ep), ".-", ms=3)
    axes[0].set(xlabel="frames", ylabel="final r of finished episodes", title="(a) reward")
    steps = [h for h in history if "train/loss" in h]  # (evaluation-only records have no loss)
    axes[1].plot([h["frames"] for h in steps], [h["train/loss"] for h in steps])
    axes[1].set(xlabel="frames", ylabel="TD loss", title="(b) loss", yscale="log")
    axes[2].plot([h["frames"] for h in steps], [h["train/epsilon"] for h in steps])
    axes[2].set(xlabel="frames", ylabel="epsilon", title="exploration")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_eval(result: dict, path: str | Path) -> Path:
    per = result["per_start"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    cmap = plt.get_cmap("viridis")
    for i, p in enumerate(per):
        color = cmap(i / max(1, len(per) - 1))
        steps = range(1, len(p["reward_path"]) + 1)
        axes[0].plot(steps, p["reward_path"], color=color, lw=1)
        axes[1].plot(steps, [a[0] for a in p["angle_path_deg"]], color=color, lw=1)
    axes[0].axhline(result["success_r"], color="k", ls="--", lw=0.8)
    axes[0].set(xlabel="step", ylabel="r", title=f"reward per start (success {result['success_rate']:.0%})")
    axes[1].set(xlabel="step", ylabel=f"{per[0]['angle']} (deg)", title="angle path")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


RULE_LABELS = {"single": "one model", "nearest": "bank, nearest K (knows K)", "max_q": "bank, highest Q (K unknown)",
               "trial": "bank, trial (K unknown)", "any_k": "one agent, measured signals (K unknown)"}


def plot_generalisation(result: dict, path: str | Path) -> Path:
    """Success rate against K for each rule of a bank evaluation (paper fig. 6)."""
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for name in RULE_LABELS:
        rule = result["rules"].get(name)
        if rule is None:
            continue
        Ks = [float(k) for k in rule["by_K"]]
        ax.plot(Ks, [v["success_rate"] for v in rule["by_K"].values()], "o-", ms=4, label=RULE_LABELS[name])
    for K in result.get("bank_K", []):
        if isinstance(K, (list, tuple)):  # a model fine-tuned over a K range
            ax.axvspan(K[0], K[1], color="0.9", zorder=0)
        else:
            ax.axvline(K, color="0.8", lw=0.8, zorder=0)
    ax.set(xlabel="birefringence K", ylabel="success rate", ylim=(-0.05, 1.05),
           title="generalisation across K" + (" (grey: K of the bank's models)" if result.get("bank_K") else ""))
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_control(out: dict, path: str | Path, cavity: int = 0, dpi: int = 110) -> Path:
    """r, K and the controlled angles over time (paper fig. 7) from a control.json.

    Left: one cavity under every controller (the hybrid's ESC phases shaded). Right: r
    averaged over the cavities, K of every cavity, and the fraction of cavities locked.
    """
    names, controlled = out["controllers"], out["controlled"]
    K = out["K"]
    T = len(K[0])
    steps = range(1, T + 1)
    fig, axes = plt.subplots(3, 2, figsize=(13, 8), sharex=True)
    colors = {n: plt.get_cmap("tab10")(i) for i, n in enumerate(names)}
    for n in names:
        tr = out["traces"][n]
        axes[0, 0].plot(steps, tr["r"][cavity], color=colors[n], lw=1, label=n)
        for j, a in enumerate(controlled):
            axes[2, 0].plot(steps, [x[j] for x in tr["angles_deg"][cavity]], color=colors[n], lw=1,
                            ls=("-", "--", ":", "-.")[j % 4], label=f"{n} {a}" if len(controlled) > 1 else n)
        mean_r = [sum(row[t] for row in tr["r"]) / len(tr["r"]) for t in range(T)]
        locked = [sum(row[t] >= out["locked_r"] for row in tr["r"]) / len(tr["r"]) for t in range(T)]
        axes[0, 1].plot(steps, mean_r, color=colors[n], lw=1, label=n)
        axes[2, 1].plot(steps, locked, color=colors[n], lw=1, label=n)
        if "mode" in tr:
            esc = tr["mode"][cavity]
            for t, m in enumerate(esc):
                if m:
                    axes[0, 0].axvspan(t + 0.5, t + 1.5, color=colors[n], alpha=0.08, lw=0)
    axes[1, 0].plot(steps, K[cavity], color="k", lw=1)
    for row in K:
        axes[1, 1].plot(steps, row, lw=0.6, alpha=0.6)
    for ax in axes.flat:
        for t in out["scenario"]["jump_times"]:
            ax.axvline(t + 1, color="0.7", lw=0.8, ls=":", zorder=0)
    axes[0, 0].axhline(out["locked_r"], color="k", ls="--", lw=0.8)
    axes[0, 0].set(ylabel="r", title=f"cavity {cavity} (shaded: hybrid under ESC)")
    axes[1, 0].set(ylabel="K")
    axes[2, 0].set(xlabel="step", ylabel="angle (deg)")
    axes[0, 1].set(ylabel="mean r", title=f"{len(K)} cavities, scenario {out['scenario']['name']}")
    axes[1, 1].set(ylabel="K (every cavity)")
    axes[2, 1].set(xlabel="step", ylabel=f"fraction with r >= {out['locked_r']:g}", ylim=(-0.05, 1.05))
    axes[0, 1].legend(fontsize=7, ncol=3, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)


# ------------------------------------------------------------------- several evaluations over K
def read_curve(spec: str) -> tuple[str, dict]:
    """``LABEL=PATH`` or ``LABEL=PATH#RULE``: the success per K of a ``laserrl-eval`` result over K
    (the label is everything before the last ``=``).

    PATH is an eval.json (or the directory holding it) of one model evaluated over K values,
    or of a bank (``bank=[...]``), whose rules (single, nearest, max_q, trial) RULE picks.
    """
    from laserrl.config import ConfigError
    from laserrl.results import as_generalisation, read_json

    label, sep, where = spec.rpartition("=")  # the label may hold "=" (K = 0.1), the path not
    if not sep or not label.strip() or not where:
        raise ConfigError(f"--curve {spec!r}: give LABEL=PATH or LABEL=PATH#RULE")
    path_text, _, rule = where.partition("#")
    path = Path(path_text)
    if path.is_dir():
        path = path / "eval.json"
    result = read_json(path, f"--curve {label}")
    try:
        rules = as_generalisation(result)["rules"]  # one model's result becomes the rule "single"
    except (ConfigError, KeyError, TypeError) as err:
        raise ConfigError(f"--curve {label}: {path} is not an evaluation over K ({err})") from None
    if not isinstance(rules, dict):
        raise ConfigError(f"--curve {label}: {path} is not an evaluation over K (its rules are not a mapping)")
    if not rule:
        if len(rules) != 1:
            raise ConfigError(f"--curve {label}: {path} is a bank evaluation; name its rule, PATH#RULE, one of {sorted(rules)}")
        rule = next(iter(rules))
    if rule not in rules:
        raise ConfigError(f"--curve {label}: {path} has no rule {rule!r}; its rules: {sorted(rules)}")
    by_K = rules[rule]["by_K"]
    try:
        points = sorted((float(K), float(v["success_rate"])) for K, v in by_K.items())
    except (TypeError, ValueError, KeyError) as err:
        raise ConfigError(f"--curve {label}: {path}#{rule}: not a success rate per K ({err})") from None
    return label.strip(), {"K": [k for k, _ in points], "success_rate": [s for _, s in points]}


def plot_over_k(panels: list[tuple[str, list[tuple[str, dict]]]], path: str | Path, bar: float | None = 0.9) -> Path:
    """Success rate against K, one panel per (title, curves); a label has one colour in every
    panel; ``bar``: a dashed line at that rate."""
    labels = list(dict.fromkeys(label for _, curves in panels for label, _ in curves))
    colors = {label: plt.get_cmap("tab10")(i % 10) for i, label in enumerate(labels)}
    rows = max(len(curves) for _, curves in panels)
    fig, axes = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 3.6 + 0.22 * rows), sharey=True, squeeze=False)
    for ax, (title, curves) in zip(axes[0], panels):
        for label, curve in curves:
            ax.plot(curve["K"], curve["success_rate"], "o-", ms=3.5, lw=1.2, color=colors[label], label=label)
        if bar is not None:
            ax.axhline(bar, color="k", ls="--", lw=0.7, zorder=0)
        ax.set(xlabel="birefringence K", title=title, ylim=(-0.05, 1.05))
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), frameon=False)
    axes[0, 0].set(ylabel="success rate")
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def main(argv: list[str] | None = None) -> int:
    """``python -m laserrl.plots over-k OUT.png [--panel TITLE] --curve LABEL=PATH[#RULE] ...``:
    each ``--curve`` goes to the panel of the last ``--panel`` before it."""
    import argparse
    import sys

    from laserrl.config import ConfigError

    parser = argparse.ArgumentParser(prog="python -m laserrl.plots")
    sub = parser.add_subparsers(dest="command", required=True)
    over_k = sub.add_parser("over-k", help="success rate per K of several laserrl-eval results, in panels")
    over_k.add_argument("out", help="the PNG to write")
    over_k.add_argument("--panel", dest="items", action="append", type=lambda t: ("panel", t), default=[],
                        help="start a panel with this title; the curves after it go there")
    over_k.add_argument("--curve", dest="items", action="append", type=lambda t: ("curve", t),
                        help="LABEL=PATH or LABEL=PATH#RULE (split at the last =): PATH an eval.json (or its directory) over K, RULE a "
                             "bank evaluation's rule (single, nearest, max_q, trial)")
    over_k.add_argument("--bar", type=float, default=0.9, help="dashed line at this success rate (default 0.9)")
    args = parser.parse_args(argv)
    try:
        panels: list[tuple[str, list]] = []
        for kind, text in args.items:
            if kind == "panel":
                panels.append((text, []))
                continue
            if not panels:
                panels.append(("", []))
            panels[-1][1].append(read_curve(text))
        empty = [title or "(untitled)" for title, curves in panels if not curves]
        if not panels or empty:
            raise ConfigError("--curve: every panel needs at least one curve" + (f"; empty: {empty}" if empty else ""))
        if not args.out.endswith(".png"):
            raise ConfigError(f"out: {args.out} is not a .png file")
        print(f"figure: {plot_over_k(panels, args.out, args.bar)}")
    except (ConfigError, OSError) as err:
        print(f"{parser.prog}: error: {err}".splitlines()[0], file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
