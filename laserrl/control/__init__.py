"""Control of the running cavity while K drifts and jumps: extremum-seeking control, the
hybrid deep RL + ESC controller, derivative-free baselines, K scenarios and the
``laserrl-control`` app (docs/control.md)."""
from laserrl.control.baselines import (Genetic, GeneticParams, HillClimb, HillClimbParams, RandomSearch,
                                       RandomSearchParams)
from laserrl.control.esc import ESCParams, ExtremumSeeking
from laserrl.control.filters import StepFilter
from laserrl.control.hybrid import MODE_ESC, MODE_RL, DeepRL, Hybrid, HybridRule
from laserrl.control.metrics import per_cavity, summarise
from laserrl.control.plant import CavityPlant
from laserrl.control.scenarios import Scenario

__all__ = [
    "CavityPlant", "ESCParams", "ExtremumSeeking", "StepFilter", "DeepRL", "Hybrid", "HybridRule", "MODE_RL",
    "MODE_ESC", "RandomSearch", "RandomSearchParams", "HillClimb", "HillClimbParams", "Genetic", "GeneticParams",
    "Scenario", "per_cavity", "summarise",
]
