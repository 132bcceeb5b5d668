"""Each baseline improves r over its start on an easy case (one smooth bump, the start on its
flank), with the incumbent re-measured under drift; bad settings name the setting."""
import numpy as np
import pytest
import torch

from laserrl.control import (Genetic, GeneticParams, HillClimb, HillClimbParams, RandomSearch, RandomSearchParams)
from laserrl.control.app import run_controllers

from plants import BumpPlant, start_angles

B, T = 8, 120


def _run(controller, K=None):
    plant = BumpPlant(B, [[-24.0]], width_deg=10.0)
    K = np.zeros((B, T)) if K is None else K
    start = start_angles(np.linspace(-45.0, -38.0, B), B)
    r0 = plant.reset(torch.as_tensor(start), torch.zeros(B))["r"].squeeze(-1).numpy()
    return r0, run_controllers({"c": controller}, plant, K, start)["c"]


@pytest.mark.parametrize("make", [
    lambda: RandomSearch(RandomSearchParams(sigma_deg=3.0, global_prob=0.1), ["alpha1"], B, seed=0),
    lambda: HillClimb(HillClimbParams(), ["alpha1"], B, seed=0),
    lambda: Genetic(GeneticParams(population=8, range_deg=[-60.0, 0.0]), ["alpha1"], B, seed=0),
], ids=["random_search", "hill_climb", "ga"])
def test_baseline_improves_r_over_its_start(make):
    controller = make()
    r0, trace = _run(controller)
    best = controller.best[:, 0]
    # the incumbent (best setting) ends near the optimum, far better than the start
    assert (np.abs(best - (-24.0)) < 4.0).all(), best
    assert (trace["r"][:, -20:].max(1) > r0 + 0.05).all()
    assert trace["r"][:, -40:].mean() > r0.mean() + 0.03


def test_hill_climb_follows_a_drifting_optimum():
    hc = HillClimb(HillClimbParams(min_step_deg=0.5), ["alpha1"], 1, seed=0)
    plant = BumpPlant(1, [[-24.0]], width_deg=10.0, K_shift_deg=-50.0)  # optimum -24 - 50 K
    K = np.linspace(0.0, 0.2, 200)[None]  # optimum -24 -> -34 deg
    run_controllers({"hc": hc}, plant, K, start_angles([-24.0], 1))
    assert abs(hc.best[0, 0] - (-34.0)) < 2.0


@pytest.mark.parametrize("cls, bad, match", [
    (RandomSearchParams, {"sigma_deg": 0.0}, "sigma_deg"), (RandomSearchParams, {"global_prob": 2.0}, "global_prob"),
    (RandomSearchParams, {"range_deg": [10.0, -10.0]}, "range_deg"),
    (HillClimbParams, {"step_deg": 8.0, "max_step_deg": 4.0}, "max_step_deg"), (HillClimbParams, {"shrink": 1.5}, "shrink"),
    (GeneticParams, {"elite": 8, "population": 8}, "elite"), (GeneticParams, {"population": 1}, "population"),
    (GeneticParams, {"mutation_prob": -0.1}, "mutation_prob"), (GeneticParams, {"population": float("inf")}, "population"),
])
def test_bad_settings_name_the_setting(cls, bad, match):
    with pytest.raises(ValueError, match=match):
        cls(**bad)
