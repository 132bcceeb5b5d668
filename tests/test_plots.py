"""python -m laserrl.plots over-k: several evaluations over K in panels, and its refusals."""
import json

import pytest

from laserrl.config import ConfigError
from laserrl.plots import main, read_curve


def _by_K(rates):
    return {f"{K:g}": {"success_rate": s, "mean_final_reward": 0.1} for K, s in rates.items()}


@pytest.fixture
def evals(tmp_path):
    one = tmp_path / "agent"
    one.mkdir()
    # one model over K, K not in order as laserrl-eval may list them (grid, then off the grid)
    (one / "eval.json").write_text(json.dumps({"success_rate": 0.5, "mean_final_reward": 0.1, "mean_steps_to_lock": 30.0,
                                               "by_K": _by_K({0.0: 1.0, 0.4: 0.2, -0.1: 0.3})}))
    bank = tmp_path / "bank.json"
    rules = {name: {"success_rate": 0.5, "mean_final_reward": 0.1, "by_K": _by_K({0.0: s, 0.2: 1.0})}
             for name, s in (("trial", 0.9), ("nearest", 0.7), ("single", 0.4))}
    bank.write_text(json.dumps({"bank": ["a", "b"], "K": [0.0, 0.2], "rules": rules}))
    return one, bank


def test_curves_read_one_model_and_a_bank_rule(evals):
    one, bank = evals
    label, curve = read_curve(f"agent={one}")
    assert label == "agent"
    assert curve["K"] == [-0.1, 0.0, 0.4] and curve["success_rate"] == [0.3, 1.0, 0.2]
    label, nearest = read_curve(f"trained at K = 0.1={bank}#nearest")
    assert label == "trained at K = 0.1" and nearest["success_rate"] == [0.7, 1.0]


def test_over_k_writes_panels(evals, tmp_path, capsys):
    one, bank = evals
    out = tmp_path / "cmp.png"
    code = main(["over-k", str(out), "--panel", "fields", "--curve", f"trial={bank}#trial",
                 "--curve", f"one={bank}#single", "--panel", "measured", "--curve", f"agent={one / 'eval.json'}"])
    assert code == 0 and out.stat().st_size > 10_000
    assert str(out) in capsys.readouterr().out


@pytest.mark.parametrize("spec, words", [
    ("no label here", "LABEL=PATH"),
    ("x={missing}", "no such file"),
    ("x={bank}", "name its rule"),
    ("x={bank}#max_q", "no rule 'max_q'"),
    ("x={notjson}", "not valid JSON"),
    ("x={notover}", "neither rules"),
    ("x={rulelist}#trial", "rules are not a mapping"),
])
def test_bad_curves_are_refused_by_name(evals, tmp_path, spec, words):
    one, bank = evals
    (tmp_path / "notjson.json").write_text("{")
    (tmp_path / "notover.json").write_text(json.dumps({"success_rate": 1.0}))
    (tmp_path / "rulelist.json").write_text(json.dumps({"rules": ["trial"]}))
    spec = spec.format(missing=tmp_path / "nope.json", bank=bank, notjson=tmp_path / "notjson.json",
                       notover=tmp_path / "notover.json", rulelist=tmp_path / "rulelist.json")
    with pytest.raises(ConfigError, match=words):
        read_curve(spec)


def test_cli_errors_are_one_line_and_write_nothing(evals, tmp_path, capsys):
    one, bank = evals
    out = tmp_path / "x.png"
    assert main(["over-k", str(out), "--panel", "empty", "--panel", "m", "--curve", f"a={one}"]) == 2
    assert main(["over-k", str(out), "--curve", f"a={bank}"]) == 2
    assert main(["over-k", str(tmp_path / "x.pdf"), "--curve", f"a={one}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and "empty" in err[0] and "name its rule" in err[1] and "x.pdf" in err[2]
    assert not out.exists()
