"""Result files of ``laserrl-eval`` read back: a JSON file named in errors by the option that
gave it, and one model's evaluation over K in the shape of a bank evaluation.

Pure functions of dicts and paths, imported by the evaluation, the plots and the report alike.
"""
from __future__ import annotations

import json
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
