"""What the report's figures and claims need, computed once from the checkpoints and result files.

Every expensive piece (a greedy evaluation, a landscape, the replayed paths) is a cached
property of ``ReportContext``, so a figure or a claim asks for it and it is computed at
most once; a report of some figures only computes what those need.
"""
from __future__ import annotations

import json
import math
import shlex
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Mapping

import torch

from laserrl.analysis import (StepSettings, cold_landscape, follow_paths, full_angles, settle, straight_path, sweep)
from laserrl.model import load_model as read_model, record_dir
from laserrl.config import ConfigError
from laserrl.envs.factory import make_params, make_task
from laserrl.envs.laser_env import ANGLE_NAMES
from laserrl.paths import CONF_DIR
from laserrl.results import as_generalisation, read_json
from laserrl.evaluate import _stage_base_angles, evaluate_bank, evaluate_policy, load_agent, write_eval

#: the angles each model of the report controls (None: any; k_base, the model the claims about
#: other K start from, is the four-controller model at K = 0.1, or zoo:siso for the single-input variant)
ROLES = {"siso": ("alpha1",), "duo": ("alpha1", "alpha2"), "miso": tuple(ANGLE_NAMES), "k_base": None,
         "any_k": tuple(ANGLE_NAMES)}  # any_k: the K-blind agent of experiment=miso_any_k (beyond the paper)
NOT_IN_ZOO = ("not backed by the zoo: no bank of models fine-tuned across K was given; give "
              "report.checkpoints.bank (the zoo's: zoo:miso-k-0.2, zoo:miso-k0, zoo:miso-k0.2, zoo:miso-k0.4) and "
              "report.results.*, or see docs/experiments.md")

APPS = {"train": "laserrl-train", "evaluate": "laserrl-eval", "app": "laserrl-report"}


def grid(spec, name: str) -> torch.Tensor:
    """[first, last, step] (deg) as the grid first, first + step, ..., last."""
    try:
        first, last, step = (float(x) for x in spec)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be [first, last, step], got {spec!r}") from None
    if not all(math.isfinite(x) for x in (first, last, step)) or step <= 0 or last <= first:
        raise ConfigError(f"{name} must have first < last and step > 0, got {spec!r}")
    count = round((last - first) / step)
    if abs(first + count * step - last) > 1e-9 * max(1.0, abs(last)):
        raise ConfigError(f"{name}: last - first must be a multiple of step, got {spec!r}")
    return first + step * torch.arange(count + 1, dtype=torch.float64)


def widen(values: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """The grid ``values`` extended by whole steps until it holds [low, high]."""
    step = float(values[1] - values[0])
    first, last = float(values[0]), float(values[-1])
    first -= step * max(0, math.ceil((first - low) / step - 1e-9))
    last += step * max(0, math.ceil((high - last) / step - 1e-9))
    return first + step * torch.arange(round((last - first) / step) + 1, dtype=torch.float64)


def producing_command(path: str | Path) -> str | None:
    """The command line that wrote ``path``, from the ``.hydra`` directory of its run (or of
    an enclosing run, e.g. a curriculum stage's); None if it was not recorded."""
    path = Path(path).resolve()
    for d in [path, *path.parents][:5]:
        overrides, hydra_yaml = d / ".hydra" / "overrides.yaml", d / ".hydra" / "hydra.yaml"
        if overrides.exists() and hydra_yaml.exists():
            from omegaconf import OmegaConf

            hydra_cfg = OmegaConf.load(hydra_yaml)
            app = APPS.get(str(OmegaConf.select(hydra_cfg, "hydra.job.name")), str(OmegaConf.select(hydra_cfg, "hydra.job.name")))
            args = [str(a) for a in OmegaConf.to_container(OmegaConf.load(overrides))]
            command = " ".join([app, *(shlex.quote(a) for a in args), f"hydra.run.dir={d}"])
            inner = path.relative_to(d)
            return command + (f"  (writes {inner})" if str(inner) != "." else "")
    return None


@dataclass
class Model:
    """A checkpoint with the role it plays in the report."""

    role: str
    path: str
    state: dict = field(repr=False)
    command: str | None = None  # the command that trained it

    @property
    def config(self) -> dict:
        return self.state["config"]

    @property
    def env_cfg(self) -> dict:
        return dict(self.config["env"])

    @property
    def stage_cfg(self) -> dict:
        """The checkpoint's stage; one saved before stages had a ``protocol`` gets the protocol
        of its stage file in laserrl/conf/stage (the same task)."""
        stage = dict(self.config["stage"])
        if not stage.get("protocol"):
            path = Path(CONF_DIR) / "stage" / f"{stage.get('name')}.yaml"
            if path.exists():
                from omegaconf import OmegaConf

                stage["protocol"] = OmegaConf.to_container(OmegaConf.load(path)).get("protocol")
        return stage

    @property
    def run_dir(self) -> Path:
        """Where the model's training record lies (history.json, eval.json): its run directory,
        or the zoo model's own directory."""
        return record_dir(self.state["dir"])

    @property
    def K(self) -> float:
        K = self.stage_cfg["K"]
        return float(K) if isinstance(K, (int, float)) else 0.5 * (float(K[0]) + float(K[1]))

    @property
    def base_deg(self) -> list[float]:
        """The stage's initial angles (the middle of a range)."""
        return _stage_base_angles(self.stage_cfg)

    @property
    def max_steps(self) -> int:
        return int(self.stage_cfg["max_steps"])


def load_model(path: str, role: str, command: str | None = None) -> Model:
    """Load the model ``path`` (zoo:NAME, a run or model directory) for ``role`` and check that
    it controls the right angles. Its command: ``command``, else its model card's, else its
    run's ``.hydra`` record."""
    state = read_model(path)
    controlled = tuple(state["config"]["stage"]["controlled"])
    if ROLES[role] is not None and controlled != ROLES[role]:
        raise ConfigError(f"report.checkpoints.{role}: {path} controls {list(controlled)}; the {role} figures need a "
                          f"model controlling {list(ROLES[role])}")
    card = state["meta"].get("card") or {}
    recorded = card.get("command") and card["command"] + (f"  ({state['path']})" if str(path).startswith("zoo:") else "")
    return Model(role, state["path"], state, command or recorded or producing_command(state["dir"]))


def frames_to_success(run_dir: Path, target: float) -> int | None:
    """Frames until the greedy success rate first reached ``target`` in a run evaluated during
    training (``train.eval_every_frames``) or, failing that, after it; None if it never did."""
    summary = json.loads((run_dir / "summary.json").read_text()) if (run_dir / "summary.json").exists() else {}
    if summary.get("frames_to_success") is not None:
        return int(summary["frames_to_success"])
    history = json.loads((run_dir / "history.json").read_text()) if (run_dir / "history.json").exists() else []
    for h in history:
        if h.get("eval/success_rate") is not None and h["eval/success_rate"] >= target:
            return int(h["frames"])
    # the evaluation after training (same protocol) counts too
    if summary.get("eval/success_rate") is not None and summary["eval/success_rate"] >= target:
        return int(summary["frames"])
    return None


def bank_entries(bank) -> list:
    """``report.checkpoints.bank`` as strings: each entry a path, or a list of paths (an ensemble,
    see ``laserrl.evaluate.evaluate_bank``)."""
    return [str(e) if isinstance(e, (str, Path)) else [str(p) for p in e] for e in bank or []]


def bank_paths(bank: list) -> list[str]:
    """Every checkpoint path of a bank, ensembles flattened, in order."""
    return [p for e in bank for p in ([e] if isinstance(e, str) else e)]


class ReportContext:
    """Checkpoints, result files and settings of one report; see the module docstring.

    Args:
        cfg: the ``report`` section of laserrl/conf/report.yaml as a plain dict.
        run_dir: where work files go.  models: role -> Model (siso, duo, miso).
        bank: the bank's entries (fig. 6), paths or lists of paths (ensembles).  commands: label -> command line of the
            runs behind the numbers ("report": this report's own command).
    """

    def __init__(self, cfg: Mapping[str, Any], run_dir: Path, models: dict[str, Model], bank: list,
                 commands: dict[str, str], seed: int = 0):
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.models = models
        self.bank = bank
        self.commands = commands
        self.seed = seed
        self.compile = bool(cfg.get("compile", False))
        self.numbers: dict[str, Any] = {}  # everything measured, written to report.json
        self.run_commands: dict[Path, str] = {}  # run dir -> command, for runs trained by this report

    def command_for(self, path: str | Path) -> str:
        """The command that wrote ``path``: a run trained by this report, else its run's ``.hydra``."""
        path = Path(path).resolve()
        for d in [path, *path.parents]:
            if d in self.run_commands:
                inner = path.relative_to(d)
                return self.run_commands[d] + (f"  (writes {inner})" if str(inner) != "." else "")
        return producing_command(path) or f"(command not recorded: {path})"

    # ---------------------------------------------------------------- physics and rollouts
    def physics(self, model: Model):
        """(CavityParams, StepSettings) of ``model``'s env: its exact per-step numerics, and the
        landscape's ``settle_round_trips``."""
        task = make_task(model.env_cfg, model.stage_cfg)
        settings = StepSettings.from_task(task, compile=self.compile,
                                          settle_round_trips=int(self.cfg["landscape"]["settle_round_trips"]))
        return make_params(model.env_cfg), settings

    def rollout(self, model: Model, **eval_overrides) -> dict:
        """Greedy rollouts of ``model`` (``laserrl.evaluate.evaluate_policy``; its stage's
        protocol unless overridden)."""
        eval_cfg = {"compile": self.compile, "plots": False, **eval_overrides}
        return evaluate_policy(lambda env: load_agent(model.state, env.action_spec_unbatched), model.env_cfg,
                               model.stage_cfg, eval_cfg, self.seed)

    def replay(self, model: Model, per_start: list[dict], record_fields: bool = True):
        """Replay evaluated rollouts through the physics with the env's semantics (the fields
        are not in eval results); the largest |r| difference to the rollout is recorded."""
        controlled = list(model.stage_cfg["controlled"])
        paths = torch.stack([full_angles(p["angle_path_deg"], controlled, p["initial_angles_deg"]) for p in per_start])
        K = torch.tensor([p["K"] for p in per_start], dtype=torch.float64)
        params, settings = self.physics(model)
        out = follow_paths(paths, K, params, settings, record_fields=record_fields)
        env_r = torch.tensor([p["reward_path"] for p in per_start], dtype=torch.float64)
        diff = float((out.r - env_r).abs().max())
        record = self.numbers.setdefault("replay_max_abs_dr", {})
        record[model.role] = max(diff, record.get(model.role, 0.0))
        return out, params

    # ---------------------------------------------------------------- fig. 2, 3: the single-input model
    @cached_property
    def history(self) -> list[dict] | None:
        path = self.models["siso"].run_dir / "history.json"
        return json.loads(path.read_text()) if path.exists() else None

    @cached_property
    def siso(self) -> dict:
        """The siso protocol's rollouts (plus the detailed starts) and the replayed details with fields."""
        m = self.models["siso"]
        details = [float(s) for s in self.cfg["fig3_starts"]]
        protocol = [float(s) for s in ((m.stage_cfg.get("protocol") or {}).get("starts_deg") or details)]
        result = self.rollout(m, starts_deg=sorted(set(protocol) | set(details)))
        rows = [p for p in result["per_start"] if p["initial_angle_deg"] in protocol]
        detail_rows = [p for p in result["per_start"] if p["initial_angle_deg"] in details and p["repeat"] == 0]
        replay, params = self.replay(m, detail_rows)
        success = sum(p["success"] for p in rows) / len(rows)
        self.numbers["siso"] = {"success_rate": success, "starts": protocol, "success_r": result["success_r"],
                                "mean_final_reward": sum(p["final_reward"] for p in rows) / len(rows),
                                "successful_starts": [p["initial_angle_deg"] for p in rows if p["success"]]}
        return {"result": result, "protocol": rows, "details": detail_rows, "replay": replay, "params": params,
                "success_rate": success}

    # ---------------------------------------------------------------- fig. 4: bistability
    @cached_property
    def alpha1_sweep(self) -> dict:
        """alpha1 swept up and down (and cold starts) at the siso model's other angles and K."""
        m = self.models["siso"]
        lc = self.cfg["landscape"]
        params, settings = self.physics(m)
        values = grid(lc["alpha1_deg"], "report.landscape.alpha1_deg")
        sw = sweep("alpha1", values, m.base_deg, m.K, params, settings)
        cold = cold_landscape("alpha1", values, m.base_deg, m.K, params, settings)[0] if lc.get("cold") else None
        self.numbers["alpha1_sweep"] = {**sw.to_dict(), "cold": None if cold is None else cold.tolist(),
                                        "min_round_trips": settings.min_round_trips,
                                        "max_round_trips": settings.max_round_trips, "tol": settings.tol}
        return {"sweep": sw, "cold": cold, "settings": settings}

    @cached_property
    def paths(self) -> dict:
        """The duo model's greedy path from its stage's start and the straight path to the same
        end in as many steps, both replayed with the env's semantics, then settled at the end."""
        m = self.models["duo"]
        controlled = list(m.stage_cfg["controlled"])
        base = m.base_deg
        start = [base[ANGLE_NAMES.index(a)] for a in controlled]
        result = self.rollout(m, starts_deg=[start[0]])
        p = result["per_start"][0]
        agent = torch.tensor(p["angle_path_deg"], dtype=torch.float64)
        straight = straight_path(start, agent[-1], agent.shape[0])
        paths4 = torch.stack([full_angles(agent, controlled, base), full_angles(straight, controlled, base)])
        params, settings = self.physics(m)
        out = follow_paths(paths4, m.K, params, settings)
        u, v, r_settled, converged = settle(out.u, out.v, torch.deg2rad(paths4[:, -1]), m.K, params, settings)
        env_r = torch.tensor(p["reward_path"], dtype=torch.float64)
        self.numbers.setdefault("replay_max_abs_dr", {})["duo"] = float((out.r[0] - env_r).abs().max())
        self.numbers["paths"] = {"start_deg": start, "end_deg": agent[-1].tolist(), "steps": agent.shape[0], "K": m.K,
                                 "agent_path_deg": agent.tolist(), "r_agent": out.r[0].tolist(),
                                 "r_straight": out.r[1].tolist(), "r_settled": r_settled.tolist(),
                                 "settled_converged": converged.tolist()}
        return {"start": start, "agent": agent, "straight": straight, "r": out.r, "u": u, "v": v,
                "r_settled": r_settled, "converged": converged, "params": params, "controlled": controlled,
                "steps_to_lock": p["steps_to_lock"]}

    @cached_property
    def alpha_map(self) -> dict:
        """alpha1 swept up and down on every alpha2 row of a grid holding both paths (duo model's stage)."""
        m = self.models["duo"]
        lc = self.cfg["landscape"]
        path = self.paths
        both = torch.cat([path["agent"], path["straight"], torch.tensor([path["start"]], dtype=torch.float64)])
        a1 = widen(grid(lc["map_alpha1_deg"], "report.landscape.map_alpha1_deg"), float(both[:, 0].min()), float(both[:, 0].max()))
        a2 = widen(grid(lc["map_alpha2_deg"], "report.landscape.map_alpha2_deg"), float(both[:, 1].min()), float(both[:, 1].max()))
        rows = torch.tensor(m.base_deg, dtype=torch.float64).repeat(a2.numel(), 1)
        rows[:, ANGLE_NAMES.index("alpha2")] = a2
        params, settings = self.physics(m)
        sw = sweep("alpha1", a1, rows, m.K, params, settings)
        self.numbers["alpha_map"] = {"alpha2_deg": a2.tolist(), **sw.to_dict()}
        return {"sweep": sw, "alpha2": a2}

    # ---------------------------------------------------------------- fig. 5: four controllers
    @cached_property
    def miso(self) -> dict:
        """The miso model from its stage's start with the paper's sech fields (replayed for the
        fields), and its stage protocol (noise draws) from its run's eval.json or evaluated here."""
        m = self.models["miso"]
        result = self.rollout(m, init_fields="sech", repeats=1)
        p = result["per_start"][0]
        replay, params = self.replay(m, [p])
        saved = m.run_dir / "eval.json"
        protocol = json.loads(saved.read_text()) if saved.exists() else None
        source = str(saved)
        if protocol is None or protocol.get("stage") != m.stage_cfg.get("name") or not protocol.get("per_start"):
            protocol, source = self.rollout(m), "report"
        self.numbers["miso"] = {"sech_start": {k: p[k] for k in ("initial_angles_deg", "final_reward", "success",
                                                                   "steps_to_lock", "reward_path")},
                                "protocol": {k: protocol.get(k) for k in ("success_rate", "mean_final_reward",
                                                                          "mean_steps_to_lock", "repeats", "steps")},
                                "protocol_source": source}
        return {"result": result, "per_start": p, "replay": replay, "params": params, "protocol": protocol,
                "protocol_source": source}

    # ---------------------------------------------------------------- fig. 6 and training numbers
    @property
    def has_generalisation(self) -> bool:
        return bool(self.cfg["results"].get("generalisation") or self.bank or "k_base" in self.models)

    @cached_property
    def generalisation(self) -> dict:
        """Success over the K grid in ``evaluate_bank``'s shape: the given eval.json (a bank's, or
        one model's over K), or evaluated here: the bank with the k_base model as ``single``,
        or the k_base model alone. ``generalisation.steps`` null: the k_base model's protocol."""
        given = self.cfg["results"].get("generalisation")
        if given:
            try:
                return as_generalisation(read_json(given, "report.results.generalisation"))
            except ConfigError as err:
                raise ConfigError(f"report.results.generalisation: {given}: {err}") from None
        eval_cfg = self._grid_eval_cfg(self.cfg["generalisation"]["K"])
        out = self.run_dir / "generalisation"
        single = self.models.get("k_base")
        if self.bank:
            return evaluate_bank(self.bank, eval_cfg, out, single=single and single.path)
        if single is None:
            raise ConfigError("report: fig. 6 needs report.checkpoints.k_base, report.checkpoints.bank or "
                              "report.results.generalisation")
        result = as_generalisation(self.rollout(single, **eval_cfg), single.path)
        write_eval(result, out, plots=False)
        return result

    def _grid_eval_cfg(self, Ks) -> dict:
        """Evaluation settings over the K values ``Ks`` (``generalisation.steps`` null: the model's protocol)."""
        eval_cfg = {"K": [float(k) for k in Ks], "compile": self.compile, "plots": False}
        if self.cfg["generalisation"].get("steps") is not None:
            eval_cfg["steps"] = int(self.cfg["generalisation"]["steps"])
        return eval_cfg

    @cached_property
    def any_k(self) -> dict | None:
        """The K-blind agent (``report.checkpoints.any_k``) on the K values and noise draws of the
        generalisation (fig. 6): its ``evaluate_policy`` result; None without the model."""
        model = self.models.get("any_k")
        if model is None:
            return None
        g = self.generalisation
        eval_cfg = self._grid_eval_cfg(g["K"])
        if g.get("seed") is not None:  # the draws the bank and the one model had
            eval_cfg["seed"] = int(g["seed"])
        result = self.rollout(model, **eval_cfg)
        write_eval(result, self.run_dir / "any_k", plots=False)
        return result

    # ---------------------------------------------------------------- fig. 7: holding the lock
    @cached_property
    def control(self) -> dict:
        """A laserrl-control control.json: the given one (``report.results.control``), or every
        controller run here on the k_base model under ``report.control`` (a small budget)."""
        given = self.cfg["results"].get("control")
        if given:
            out = read_json(given, "report.results.control")
            self.commands.setdefault("control", self.command_for(given))
        else:
            from laserrl.control.app import run_control
            from laserrl.report.spot import compose_train_config

            if "k_base" not in self.models:
                raise ConfigError("report: fig. 7 needs report.checkpoints.k_base or report.results.control")
            overrides = [f"checkpoint={self.models['k_base'].path}", f"seed={self.seed}", "progress=false",
                         "plots=false", f"compile={self.compile}", *self.cfg["control"]]
            cfg = compose_train_config(overrides, config_name="control")
            run_dir = self.run_dir / "control"
            cfg.run_dir = str(run_dir)  # compose leaves hydra:runtime unset
            out = run_control(cfg)
            self.commands.setdefault("control", "laserrl-control " + " ".join(shlex.quote(o) for o in overrides))
        results = out["results"]
        if "hybrid" not in results:
            raise ConfigError("report: fig. 7 needs a control run with the hybrid controller (controller=all or hybrid)")
        self.numbers["control"] = {"scenario": out["scenario"].get("name"), "num_cavities": out["num_cavities"],
                                   **{n: {k: (r["summary"].get(k) or {}).get("mean")
                                          for k in ("frac_locked", "locked_after_first_lock", "mean_r")}
                                      for n, r in results.items()}}
        return out

    @cached_property
    def transfer(self) -> list[dict]:
        """Fine-tuning rows of the transfer.json files: K, frames and episodes to success."""
        rows = []
        for path in self.cfg["results"].get("transfer") or []:
            data = read_json(path, "report.results.transfer")
            for row in data["rows"]:
                ft = row["finetune"]
                sub = Path(path).parent / f"K{row['K']:+.2f}-finetune"
                try:
                    max_steps = int(read_model(sub)["config"]["stage"]["max_steps"])
                except Exception:  # the sub-run's checkpoint is gone: frames only
                    max_steps = None
                frames = ft["frames_to_success"]
                rows.append({"K": float(row["K"]), "frames_to_success": frames, "frames": ft["frames"],
                             "max_steps": max_steps, "file": str(path),
                             "episodes_to_success": None if frames is None or max_steps is None else frames / max_steps,
                             "episodes": None if max_steps is None else ft["frames"] / max_steps})
        self.numbers["transfer"] = rows
        return rows

    @cached_property
    def train_to_success(self) -> list[dict]:
        """Runs at K = 0.1 evaluated during training: frames and episodes until success >= 0.9
        (the given run dirs, and the siso model's own run if it was evaluated during training)."""
        dirs = [Path(d) for d in self.cfg["results"].get("train_to_success") or []]
        own = self.models["siso"].run_dir
        if self.history and any("eval/success_rate" in h for h in self.history) and own not in dirs:
            dirs.append(own)
        rows = []
        for d in dirs:
            if not (d / "summary.json").exists():
                raise ConfigError(f"report.results.train_to_success: {d} has no summary.json (not a finished training run)")
            state = read_model(d)
            target = state["config"]["train"].get("stop_at_success") or 0.9
            frames = frames_to_success(d, target)
            max_steps = int(state["config"]["stage"]["max_steps"])
            rows.append({"run_dir": str(d), "K": state["config"]["stage"]["K"], "target": target, "frames": frames,
                         "episodes": None if frames is None else frames / max_steps, "max_steps": max_steps,
                         "frames_trained": int(state["frames"]), "command": self.command_for(d)})
        self.numbers["train_to_success"] = rows
        return rows
