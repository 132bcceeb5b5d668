"""``laserrl-eval checkpoint=PATH``: the paper's inference protocol with a trained agent.

Greedy rollouts of ``eval.steps`` (20) agent steps from every initial angle in
``eval.starts_deg`` (alpha1 in {-40, -38, ..., -10} deg), sech initial fields, at
each K in ``eval.K`` (the checkpoint's K unless given). Success for one start:
final r >= ``eval.success_r`` (0.18). Writes ``eval.json`` (and a plot) into the
run directory and prints its path.

    laserrl-eval checkpoint=outputs/2026-11-22/10-00-00/checkpoints/last.pt
    laserrl-eval checkpoint=RUN_DIR eval.K=0.2           # any K
    laserrl-eval checkpoint=RUN_DIR 'eval.K=[0,0.1,0.2]'  # several K at once
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tensordict import TensorDict

from laserrl.agents.dqn import make_actor, make_qnet
from laserrl.checkpoint import CheckpointError, load_checkpoint
from laserrl.config import ConfigError, user_errors
from laserrl.envs.factory import make_env
from laserrl.envs.laser_env import ANGLE_NAMES

CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")


def load_agent(state: Mapping[str, Any], action_spec):
    """Rebuild the greedy actor of a checkpoint for an env with ``action_spec``."""
    cfg = state["config"]
    net = cfg["agent"]["network"]
    n_env = int(action_spec.n)
    if int(state["num_actions"]) != n_env:
        raise CheckpointError(
            f"checkpoint {state.get('path')} has a {state['num_actions']}-action head (stage {state.get('stage')}); "
            f"this task needs {n_env} actions"
        )
    qnet = make_qnet(n_env, int(cfg["env"].get("physics", {}).get("n", 256)), net["channels"], net["kernel_size"],
                     net["pool"], net["hidden"], net["negative_slope"])
    try:
        qnet.load_state_dict(state["qnet"])
    except RuntimeError as err:
        raise CheckpointError(f"checkpoint {state.get('path')} does not match its network config: {str(err).splitlines()[0]}") from None
    qnet.eval()
    return make_actor(qnet, action_spec)


def _as_list(x) -> list[float]:
    if x is None:
        return []
    if isinstance(x, (int, float)):
        return [float(x)]
    return [float(v) for v in x]


def evaluate_checkpoint(checkpoint: str, eval_cfg: Mapping[str, Any], out_dir: str | Path, stage: Mapping | None = None) -> dict:
    """Run the protocol; returns and writes the eval.json content."""
    state = load_checkpoint(checkpoint)
    cfg = state["config"]
    stage_cfg = dict(stage) if stage is not None else dict(cfg["stage"])
    env_cfg = dict(cfg["env"])
    if eval_cfg.get("max_round_trips"):
        env_cfg["max_round_trips"] = int(eval_cfg["max_round_trips"])
    if eval_cfg.get("dtype"):
        env_cfg["dtype"] = eval_cfg["dtype"]
    env_cfg["compile"] = bool(eval_cfg.get("compile", env_cfg.get("compile", False)))
    steps = int(eval_cfg["steps"])
    if steps < 1:
        raise ConfigError(f"eval.steps must be >= 1, got {steps}")
    threshold = float(eval_cfg["success_r"])
    Ks = _as_list(eval_cfg.get("K"))
    if not Ks:
        K_stage = stage_cfg["K"]
        Ks = [float(K_stage)] if isinstance(K_stage, (int, float)) else [0.5 * (float(K_stage[0]) + float(K_stage[1]))]
    first = stage_cfg["controlled"][0]
    starts = _as_list(eval_cfg.get("starts_deg"))
    base = []
    for name in ANGLE_NAMES:
        v = stage_cfg["init_angles_deg"][name]
        base.append(float(v) if isinstance(v, (int, float)) else 0.5 * (float(v[0]) + float(v[1])))
    if not starts:
        starts = [base[ANGLE_NAMES.index(first)]]
    combos = [(K, s) for K in Ks for s in starts]
    B = len(combos)
    env = make_env(env_cfg, stage_cfg, B, int(cfg.get("seed", 0)), centred=False, max_steps=steps,
                   init_fields=eval_cfg.get("init_fields") or stage_cfg.get("init_fields", "sech"))
    actor = load_agent(state, env.action_spec_unbatched)
    init = torch.tensor([base] * B, dtype=torch.float64)
    init[:, ANGLE_NAMES.index(first)] = torch.tensor([s for _, s in combos], dtype=torch.float64)
    reset_td = TensorDict(init_angles=torch.deg2rad(init), init_K=torch.tensor([K for K, _ in combos], dtype=torch.float64),
                          batch_size=[B])
    td = env.reset(reset_td)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(steps, actor, auto_reset=False, tensordict=td)
    r = rollout["next", "r"].squeeze(-1)  # (B, steps)
    angles = torch.rad2deg(rollout["next", "angles"].double())  # (B, steps, 4)
    ctrl = [ANGLE_NAMES.index(n) for n in stage_cfg["controlled"]]
    per_start = []
    for i, (K, s) in enumerate(combos):
        locked = (r[i] >= threshold).nonzero().flatten()
        per_start.append({
            "K": K, "initial_angle_deg": s, "angle": first,
            "initial_angles_deg": init[i].tolist(),
            "final_reward": float(r[i, -1]),
            "steps_to_lock": int(locked[0]) + 1 if locked.numel() else None,
            "reward_path": [float(x) for x in r[i]],
            "angle_path_deg": [[float(a) for a in angles[i, t, ctrl]] for t in range(steps)],
        })
    final = r[:, -1]
    success = final >= threshold
    locks = [p["steps_to_lock"] for p in per_start if p["final_reward"] >= threshold and p["steps_to_lock"] is not None]
    by_K = {}
    for K in Ks:
        rows = [p for p in per_start if p["K"] == K]
        by_K[f"{K:g}"] = {"success_rate": sum(p["final_reward"] >= threshold for p in rows) / len(rows),
                          "mean_final_reward": sum(p["final_reward"] for p in rows) / len(rows)}
    result = {
        "checkpoint": state["path"], "stage": stage_cfg.get("name"), "steps": steps, "success_r": threshold,
        "max_round_trips": env_cfg["max_round_trips"], "K": Ks,
        "success_rate": float(success.float().mean()), "mean_final_reward": float(final.mean()),
        "mean_steps_to_lock": (sum(locks) / len(locks)) if locks else None,
        "by_K": by_K, "per_start": per_start,
    }
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "eval.json"
    path.write_text(json.dumps(result, indent=1))
    if eval_cfg.get("plots", True):
        from laserrl.plots import plot_eval

        plot_eval(result, out_dir / "eval_rewards.png")
    print(f"eval: {path}")
    return result


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="eval")
def _hydra_main(cfg: DictConfig) -> float:
    with user_errors("laserrl-eval"):
        if cfg.checkpoint is None or cfg.checkpoint == "":
            raise ConfigError("give the checkpoint to evaluate: laserrl-eval checkpoint=PATH")
        stage = OmegaConf.to_container(cfg.stage, resolve=True) if cfg.get("stage") else None
        result = evaluate_checkpoint(cfg.checkpoint, OmegaConf.to_container(cfg.eval, resolve=True), cfg.run_dir, stage)
    return float(result["success_rate"])


def main() -> None:
    _hydra_main()


if __name__ == "__main__":
    main()
