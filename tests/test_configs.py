"""Every config under conf/ composes, and the composed training configs pass the checks."""
import re
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from laserrl.experiments import curriculum_stage_configs
from laserrl.train import check_train_config
from laserrl.envs.factory import make_params, make_task
from laserrl.model import zoo_names
from laserrl.paths import CONF_DIR

CONF = Path(CONF_DIR)
# groups of laserrl-control (conf/control.yaml) compose there: tests/control/test_app.py
CONTROL_GROUPS = ("controller", "scenario")
APP_CONFIG = {"train": "config", "eval": "eval", "control": "control"}


def experiment_app(name: str) -> str:
    """The command an experiment file is for, from its how-to-run lines (laserrl-train|eval|control experiment=NAME)."""
    text = (CONF / "experiment" / f"{name}.yaml").read_text()
    found = re.findall(rf"^#.*laserrl-(train|eval|control)\b.*experiment=\[?[\w,]*\b{name}\b", text, re.M)
    assert found, f"experiment/{name}.yaml does not say how to run it (laserrl-... experiment={name})"
    assert len(set(found)) == 1, f"experiment/{name}.yaml names several commands: {sorted(set(found))}"
    return found[0]


EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
GROUPS = {g.name: [o for o in sorted(p.stem for p in g.glob("*.yaml"))
                   if g.name != "experiment" or experiment_app(o) == "train"]
          for g in CONF.iterdir() if g.is_dir() and g.name not in CONTROL_GROUPS}


def _compose(overrides, name="config"):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


@pytest.mark.parametrize("group, option", [(g, o) for g, opts in GROUPS.items() for o in opts])
def test_every_group_option_composes_and_builds(group, option):
    cfg = _compose([f"{group}={option}"])
    check_train_config(cfg)
    container = OmegaConf.to_container(cfg.env, resolve=True)
    make_params(container)  # physics values are valid CavityParams
    task = make_task(container, OmegaConf.to_container(cfg.stage, resolve=True))
    assert task.num_actions == 3 ** len(cfg.stage.controlled)


CURRICULA = [n for n in GROUPS["experiment"] if _compose([f"experiment={n}"]).get("curriculum")]


@pytest.mark.parametrize("name", CURRICULA)
def test_every_curriculum_stage_config_passes_the_checks(name):
    """Each stage of a curriculum trains with its own merged config (stage file, stage_overrides,
    config_overrides, budgets); run_curriculum checks them all before the first stage trains."""
    cfg = _compose([f"experiment={name}", "run_dir=unused"])
    stages = curriculum_stage_configs(cfg)
    assert [n for n, _ in stages] == list(cfg.curriculum.stages)
    for stage_name, sub in stages:
        assert sub.stage.name == stage_name and "curriculum" not in sub
        check_train_config(sub)


@pytest.mark.parametrize("name", [n for n in EXPERIMENTS if experiment_app(n) != "train"])
def test_eval_and_control_experiments_compose_with_their_command(name):
    app = experiment_app(name)
    cfg = _compose([f"experiment={name}"], name=APP_CONFIG[app])
    # the model to run is the user's to give, or one the package ships (runs as written on a fresh install)
    assert "checkpoint" in cfg
    named = [cfg.checkpoint] + list(cfg.get("bank") or [])
    for model in (m for m in named if m is not None):
        assert model.startswith("zoo:") and model[4:] in zoo_names(), f"experiment/{name}.yaml names {model}"
    if app == "eval":  # the paper's K grid, -0.2 ... 0.4 in steps of 0.05 (other K after it)
        assert cfg.stage.name == "miso" and list(cfg.eval.K[:13]) == pytest.approx([-0.2 + 0.05 * i for i in range(13)])
    else:
        assert cfg.scenario.bounds == [-0.2, 0.4] and cfg.controller.name == "all"


def test_default_is_the_papers_single_input_task():
    cfg = _compose([])
    assert cfg.stage.name == "siso" and list(cfg.stage.controlled) == ["alpha1"]
    assert cfg.stage.K == 0.1 and list(cfg.stage.steps_deg) == [2.0]
    assert cfg.agent.exploration.kind == "exponential" and cfg.agent.target.kind == "soft"
    assert cfg.replay.kind == "prioritized" and cfg.logger.backend == "wandb" and cfg.logger.mode == "offline"


def test_eval_config_composes():
    cfg = _compose(["checkpoint=x.pt"], name="eval")
    # null: the evaluated stage's protocol
    assert cfg.eval.steps is None and cfg.eval.starts_deg is None and cfg.eval.success_r is None


@pytest.mark.parametrize("stage, steps, n_starts, success_r, hold_r, repeats", [
    ("siso", 20, 16, 0.18, None, 1),     # the paper's single-input protocol
    ("duo", 40, 5, 0.15, 0.1, 1),
    ("miso", 100, 1, 0.15, 0.1, 10),     # from 15, -5, 20, 84 deg, ten noise draws
])
def test_stage_protocols(stage, steps, n_starts, success_r, hold_r, repeats):
    p = _compose([f"stage={stage}"]).stage.protocol
    assert (p.steps, len(p.starts_deg), p.success_r, p.hold_r, p.repeats) == (steps, n_starts, success_r, hold_r, repeats)


def test_unknown_key_is_rejected_by_hydra():
    with pytest.raises(Exception, match="nosuchkey"):
        _compose(["optim.nosuchkey=1"])


def test_long_recipe_lengthens_only_the_four_controller_stage_episodes_and_validation():
    """experiment=miso_any_k_gru_long adds 200-step episodes and validation to the wide recipe's miso
    stage without dropping what it inherits (K range, validation K, drift, the earlier stages' lengths)."""
    long, wide = (_compose([f"experiment={n}"]).curriculum for n in ("miso_any_k_gru_long", "miso_any_k_gru_wide"))
    assert long.stage_overrides.miso.max_steps == 200 and "max_steps" not in wide.stage_overrides.miso
    assert long.config_overrides.miso.eval.steps == 200
    assert list(long.stage_overrides.miso.K) == [-0.25, 0.45] and long.stage_overrides.miso.K_drift == 0.005
    assert list(long.config_overrides.miso.eval.K) == list(wide.config_overrides.miso.eval.K)
    assert long.config_overrides.miso.train == wide.config_overrides.miso.train
    assert "siso" not in long.stage_overrides and long.total_frames == wide.total_frames


def test_held_recipe_validates_held_locks_over_the_grid():
    """experiment=miso_any_k_gru_held keeps the wide recipe and validates its four-controller stage
    on the comparison's 13 grid K, asking for locks held over the last 20 of the 100 steps."""
    held, wide = (_compose([f"experiment={n}", "run_dir=unused"]) for n in ("miso_any_k_gru_held", "miso_any_k_gru_wide"))
    (_, miso), = [(n, c) for n, c in curriculum_stage_configs(held) if n == "miso"]
    assert list(miso.eval.K) == pytest.approx([-0.2 + 0.05 * i for i in range(13)])
    assert miso.eval.held_steps == 20 and miso.eval.repeats == 2 and miso.stage.protocol.steps == 100
    assert held.curriculum.stage_overrides == wide.curriculum.stage_overrides
    assert held.curriculum.config_overrides.miso.train == wide.curriculum.config_overrides.miso.train


def _recipe_stages(experiment: str) -> dict:
    """{stage name: composed stage config} of a curriculum recipe."""
    return dict(curriculum_stage_configs(_compose([f"experiment={experiment}", "run_dir=unused"])))


def _assert_stages_differ_only_in(stages: dict, base: dict, *keys: str) -> None:
    """Each stage config equals the base recipe's once its ``keys`` (dotted paths, as
    ``stage.K``) are set to the base's."""
    assert stages.keys() == base.keys()
    for name, sub in stages.items():
        for key in keys:
            OmegaConf.update(sub, key, OmegaConf.select(base[name], key), merge=False)
        assert sub == base[name], name


def test_move_cost_recipe_charges_moves_only_in_the_four_controller_stage():
    """experiment=miso_any_k_gru_move_cost is the held recipe with stage.move_cost > 0 in its
    four-controller stage; the single- and two-controller stages keep the paper's reward."""
    stages = _recipe_stages("miso_any_k_gru_move_cost")
    assert stages["miso"].stage.move_cost > 0
    assert stages["siso"].stage.move_cost == stages["duo"].stage.move_cost == 0
    _assert_stages_differ_only_in(stages, _recipe_stages("miso_any_k_gru_held"), "stage.move_cost")


def test_lock_cost_recipe_is_the_move_cost_recipe_charged_only_from_a_lock():
    """experiment=miso_any_k_gru_lock_cost charges the cost recipe's move cost only for moves from
    a state at or above the measured reward's lock level, in its four-controller stage only."""
    stages, cost_stages = _recipe_stages("miso_any_k_gru_lock_cost"), _recipe_stages("miso_any_k_gru_move_cost")
    assert stages["miso"].stage.move_cost == cost_stages["miso"].stage.move_cost > 0
    assert stages["miso"].stage.move_cost_from == pytest.approx(0.454)
    assert stages["siso"].stage.move_cost_from is None and stages["duo"].stage.move_cost_from is None
    _assert_stages_differ_only_in(stages, cost_stages, "stage.move_cost_from")


def test_large_lock_cost_recipe_is_the_lock_cost_recipe_with_a_larger_cost():
    """experiment=miso_any_k_gru_lock_cost_large charges 0.05 instead of the lock cost recipe's 0.02
    for moves from a lock, still only in its four-controller stage and only from the same level."""
    stages, lock = _recipe_stages("miso_any_k_gru_lock_cost_large"), _recipe_stages("miso_any_k_gru_lock_cost")
    assert stages["miso"].stage.move_cost == pytest.approx(0.05)
    assert lock["miso"].stage.move_cost == pytest.approx(0.02)
    assert stages["miso"].stage.move_cost_from == lock["miso"].stage.move_cost_from
    assert stages["siso"].stage.move_cost == stages["duo"].stage.move_cost == 0
    _assert_stages_differ_only_in(stages, lock, "stage.move_cost")


def test_jumps_recipe_is_the_wide_recipe_with_more_jumps_of_K():
    """experiment=miso_any_k_gru_wide_jumps raises the four-controller stage's probability of a jump
    of K per step above the wide recipe's and changes nothing else."""
    stages, wide = _recipe_stages("miso_any_k_gru_wide_jumps"), _recipe_stages("miso_any_k_gru_wide")
    assert stages["miso"].stage.K_jump > wide["miso"].stage.K_jump > 0
    assert stages["siso"].stage.K_jump == stages["duo"].stage.K_jump == 0
    _assert_stages_differ_only_in(stages, wide, "stage.K_jump")


def test_coarse_recipe_is_the_wide_recipe_searching_in_coarser_steps_below_the_lock_level():
    """experiment=miso_any_k_gru_wide_coarse turns the four-controller stage's plates by 1 deg from
    states below the measured lock level and by the wide recipe's 0.5 deg from it on; nothing else."""
    stages, wide = _recipe_stages("miso_any_k_gru_wide_coarse"), _recipe_stages("miso_any_k_gru_wide")
    assert list(stages["miso"].stage.steps_deg) == [1.0] * 4
    assert list(stages["miso"].stage.fine_steps_deg) == list(wide["miso"].stage.steps_deg) == [0.5] * 4
    assert stages["miso"].stage.fine_from == pytest.approx(0.454)
    assert all(stages[n].stage.fine_from is None for n in ("siso", "duo"))
    _assert_stages_differ_only_in(stages, wide, "stage.steps_deg", "stage.fine_steps_deg", "stage.fine_from")


def test_wider_recipe_is_the_wide_recipe_over_a_wider_K_range():
    """experiment=miso_any_k_gru_wider trains the four-controller stage over K in [-0.3, 0.5] and is
    otherwise the wide recipe, its validation still on K of the comparison's [-0.2, 0.4]."""
    stages, wide = _recipe_stages("miso_any_k_gru_wider"), _recipe_stages("miso_any_k_gru_wide")
    assert list(stages["miso"].stage.K) == [-0.3, 0.5] and list(wide["miso"].stage.K) == [-0.25, 0.45]
    assert min(stages["miso"].eval.K) == -0.2 and max(stages["miso"].eval.K) == 0.4
    _assert_stages_differ_only_in(stages, wide, "stage.K")


def test_additive_recipe_is_the_wide_recipe_with_an_additive_q_head_in_every_stage():
    """experiment=miso_any_k_gru_wide_additive gives every stage's Q-network the additive head (so the
    curriculum's warm starts grow it) and changes nothing else."""
    stages, wide = _recipe_stages("miso_any_k_gru_wide_additive"), _recipe_stages("miso_any_k_gru_wide")
    for name, sub in stages.items():
        assert sub.agent.network.head == "additive" and wide[name].agent.network.head == "joint"
    _assert_stages_differ_only_in(stages, wide, "agent.network.head")


def test_spread_recipe_is_the_additive_recipe_on_a_wider_cavity_spread_in_every_stage():
    """experiment=miso_any_k_gru_wide_additive_spread trains every stage on cavities within +-15 % of
    the nominal one, wider than the +-10 % of the mismatch bar and of the additive recipe, and changes
    nothing else (its validation stays on the nominal cavity)."""
    stages, additive = _recipe_stages("miso_any_k_gru_wide_additive_spread"), _recipe_stages("miso_any_k_gru_wide_additive")
    for name, sub in stages.items():
        assert sub.env.physics_spread == pytest.approx(0.15) and additive[name].env.physics_spread == pytest.approx(0.1)
        assert sub.eval.get("physics_spread") is None
    _assert_stages_differ_only_in(stages, additive, "env.physics_spread")
