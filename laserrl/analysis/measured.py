"""How well a reward from measured signals stands in for the paper's r = E / M4.

Draws ``states`` cavities with random plate angles (uniform over [-90, 90) deg each) and K
(uniform in ``K_range``), runs each from white noise to convergence, and compares the paper's r
of the settled state with the measured reward (``laserrl.physics.instruments``) of each kind:
the Spearman rank correlation over all states, and how well the measured reward tells the
mode-locked states (r >= 0.15, and r >= 0.1) from the others (ROC AUC: the probability that a
mode-locked state scores higher than one that is not).

    python -m laserrl.analysis.measured                    # 400 states, seed 0 (docs/measured.md)
    python -m laserrl.analysis.measured --states 64 --seed 1
"""
from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import torch
from scipy.stats import mannwhitneyu, spearmanr

from laserrl.physics import CavityParams, noise_fields, reward_terms, run_to_convergence
from laserrl.physics.instruments import Instruments, measure, measured_reward


def roc_auc(score: np.ndarray, positive: np.ndarray) -> float | None:
    """P(score of a positive > score of a negative), ties counting half; None without both classes."""
    if positive.all() or not positive.any():
        return None
    return float(mannwhitneyu(score[positive], score[~positive]).statistic / (positive.sum() * (~positive).sum()))


def separating_threshold(score: np.ndarray, positive: np.ndarray) -> float | None:
    """The score above which states count as positive that best separates the two classes
    (Youden's J: the largest true-positive rate minus false-positive rate), midway between
    neighbouring scores; None without both classes."""
    if positive.all() or not positive.any():
        return None
    order = np.sort(np.unique(score))
    cuts = 0.5 * (order[1:] + order[:-1])
    j = [(score[positive] >= c).mean() - (score[~positive] >= c).mean() for c in cuts]
    return float(cuts[int(np.argmax(j))])


def settled_states(states: int, seed: int, params: CavityParams, K_range=(-0.2, 0.4), round_trips: int = 300):
    """(u, v, r) of ``states`` cavities settled from noise at random angles and K (complex128)."""
    g = torch.Generator().manual_seed(seed)
    angles = torch.deg2rad((torch.rand(states, 4, generator=g, dtype=torch.float64) - 0.5) * 180)
    K = K_range[0] + (K_range[1] - K_range[0]) * torch.rand(states, generator=g, dtype=torch.float64)
    u, v = noise_fields(states, params, g, dtype=torch.complex128)
    res = run_to_convergence(u, v, angles, K, params, tol=1e-6, max_round_trips=round_trips, min_round_trips=2)
    return res.u, res.v, reward_terms(res.u, res.v, params)[2]


def reward_agreement(states: int = 400, seed: int = 0, instruments: Instruments | None = None,
                     params: CavityParams | None = None, round_trips: int = 300) -> dict:
    """Agreement of each measured reward with the paper's r (module docstring)."""
    params = params or CavityParams()
    instruments = instruments or Instruments()
    u, v, r = settled_states(states, seed, params, round_trips=round_trips)
    m = measure(u, v, params, instruments, generator=torch.Generator().manual_seed(seed + 1))
    r_np = r.numpy()
    out = {"states": states, "seed": seed, "instruments": dataclasses.asdict(instruments),
           "locked": {"r>=0.15": int((r_np >= 0.15).sum()), "r>=0.1": int((r_np >= 0.1).sum())}, "rewards": {}}
    kinds = ["autocorrelation", "spectrum"] if instruments.autocorrelation_points else ["spectrum"]
    for kind in kinds:
        score = torch.nan_to_num(measured_reward(m, kind), nan=0.0).numpy()
        out["rewards"][kind] = {
            "spearman": float(spearmanr(score, r_np).statistic),
            "auc_r>=0.15": roc_auc(score, r_np >= 0.15), "auc_r>=0.1": roc_auc(score, r_np >= 0.1),
            # the measured reward's scale: its median over the states with r >= 0.15 and below 0.02
            "median_locked": float(np.median(score[r_np >= 0.15])) if (r_np >= 0.15).any() else None,
            "median_r<0.02": float(np.median(score[r_np < 0.02])) if (r_np < 0.02).any() else None,
            # the measured reward's levels that stand for r = 0.15 and r = 0.1 (a controller's lock thresholds)
            "threshold_r>=0.15": separating_threshold(score, r_np >= 0.15),
            "threshold_r>=0.1": separating_threshold(score, r_np >= 0.1)}
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--states", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--round-trips", type=int, default=300)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    out = reward_agreement(args.states, args.seed, round_trips=args.round_trips)
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
