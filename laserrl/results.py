"""Result files of ``laserrl-eval`` read back: a JSON file named in errors by the option that
gave it, and one model's evaluation over K in the shape of a bank evaluation.

Pure functions of dicts and paths, imported by the evaluation, the plots and the report alike.
"""
from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any, Mapping

from laserrl.validate import ConfigError


def read_json(path: str | Path, key: str) -> Any:
    """The JSON in ``path``; a directory, a missing file or invalid JSON is one ConfigError naming ``key``."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{key}: {path} is a directory; give the JSON file")
    if not path.exists():
        raise ConfigError(f"{key}: no such file {path}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ConfigError(f"{key}: {path} is not valid JSON ({err})") from None


def summary(result: Mapping[str, Any]) -> dict:
    """What a bank evaluation keeps of one rule's ``evaluate_policy`` result."""
    return {k: result[k] for k in ("success_rate", "mean_final_reward", "mean_steps_to_lock", "by_K")}


def grid_success(rules: Mapping[str, dict], num_K: int) -> dict[str, float]:
    """Per rule, the fraction of the grid's K at which it succeeds on at least 90 % of the starts."""
    return {name: sum(v["success_rate"] >= 0.9 for v in rule["by_K"].values()) / num_K for name, rule in rules.items()}


def as_generalisation(result: Mapping[str, Any], single: str | None = None) -> dict:
    """A result over a K grid in the shape of ``evaluate_bank``'s: a bank evaluation as it is,
    and one model's ``evaluate_policy`` result (``laserrl-eval checkpoint=M 'eval.K=[...]'``)
    as the rule ``single`` of a bank without members."""
    if "rules" in result:
        return dict(result)
    if "by_K" not in result:
        raise ConfigError("not an evaluation over K: it has neither rules (a bank evaluation) nor by_K")
    Ks = [float(k) for k in result["by_K"]]
    rules = {"single": summary(result)}
    return {"bank": [], "bank_K": [], "single": single, "K": Ks, "stage": result.get("stage"), "seed": result.get("seed"),
            "rules": rules, "grid_success": grid_success(rules, len(Ks))}


def failure_modes(result: Mapping[str, Any]) -> dict:
    """How the failed rollouts of an ``evaluate_policy`` result failed, from its ``per_start``.

    A failed rollout either never locked (no ``steps_to_lock``: r never reached ``success_r``) or
    locked and lost it; with a hold level (``hold_r``, the four-controller protocol) the lock counts as lost at the
    first step after the first lock where r < ``hold_r``, and ``steps_locked_before_loss`` gives
    the median, least and most steps from the first lock to that step; with ``held_steps`` a lock
    that is never lost but comes too late to be held that long counts as ``locked_late``
    (also per K). ``hold_action_after_lock``
    is the fraction of steps after the first lock, over every rollout that locked, on which no
    controlled angle moved (the all-hold action). ``by_K``: the two counts per K.
    """
    hold_r = result.get("hold_r")
    late_counted = bool(result.get("held_steps"))
    never, lost, late, locked_steps, by_K = 0, 0, 0, [], {}
    held, moved = 0, 0
    for p in result["per_start"]:
        r = p["reward_path"]
        first = None if p["steps_to_lock"] is None else p["steps_to_lock"] - 1  # the step index of the first lock
        if first is not None:
            path = p["angle_path_deg"]
            still = [all(a == b for a, b in zip(path[t - 1], path[t])) for t in range(first + 1, len(path))]
            held += sum(still)
            moved += len(still) - sum(still)
        if p["success"]:
            continue
        counts = by_K.setdefault(f"{float(p['K']):g}", {"never_locked": 0, "lost": 0,
                                                        **({"locked_late": 0} if late_counted else {})})
        if first is None:
            never += 1
            counts["never_locked"] += 1
            continue
        drop = None
        if hold_r is not None:
            drop = next((t for t in range(first + 1, len(r)) if r[t] < float(hold_r)), None)
        if late_counted and drop is None:  # held to the end, from too late a lock
            late += 1
            counts["locked_late"] += 1
            continue
        lost += 1
        counts["lost"] += 1
        if drop is not None:
            locked_steps.append(drop - first)
    spread = ({"median": statistics.median(locked_steps), "min": min(locked_steps), "max": max(locked_steps)}
              if locked_steps else None)
    return {"failed": never + lost + late, "never_locked": never, "lost": lost,
            **({"locked_late": late} if late_counted else {}), "steps_locked_before_loss": spread,
            "hold_action_after_lock": held / (held + moved) if held + moved else None,
            "by_K": dict(sorted(by_K.items(), key=lambda kv: float(kv[0])))}


def failure_line(failures: Mapping[str, Any]) -> str:
    """One line of ``failure_modes``' counts, as laserrl-eval prints them."""
    text = f"failed {failures['failed']}: never locked {failures['never_locked']}, locked and lost it {failures['lost']}"
    spread = failures.get("steps_locked_before_loss")
    if spread:
        text += f" (after {spread['median']:g} steps locked, median; {spread['min']}-{spread['max']})"
    if failures.get("locked_late") is not None:
        text += f", locked too late {failures['locked_late']}"
    if failures.get("hold_action_after_lock") is not None:
        text += f"; all-hold action on {100 * failures['hold_action_after_lock']:.1f} % of the steps after a lock"
    return text
