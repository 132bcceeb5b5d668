"""Batched physics of the NPR mode-locked fiber laser (pure torch, no RL imports)."""
from laserrl.physics.cavity import propagate, round_trip
from laserrl.physics.fields import noise_fields, sech_fields
from laserrl.physics.jones import apply_jones, cavity_jones
from laserrl.physics.observables import amplitude, convergence, reward_terms, trapezoid_energy
from laserrl.physics.params import CavityParams
from laserrl.physics.run import ConvergenceResult, NonFiniteFieldError, check_finite, run_to_convergence

__all__ = [
    "CavityParams", "propagate", "round_trip", "trapezoid_energy", "sech_fields", "noise_fields",
    "apply_jones", "cavity_jones", "amplitude", "convergence", "reward_terms",
    "ConvergenceResult", "NonFiniteFieldError", "check_finite", "run_to_convergence",
]
