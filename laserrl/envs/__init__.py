"""TorchRL environments over the batched cavity physics."""
from laserrl.envs.actions import action_to_deltas, deltas_to_action, hold_action, num_actions
from laserrl.envs.laser_env import ANGLE_NAMES, LaserCavityEnv, LaserTask, wrap_angle
from laserrl.envs.transforms import centred_reward

__all__ = [
    "ANGLE_NAMES", "LaserCavityEnv", "LaserTask", "wrap_angle", "action_to_deltas", "deltas_to_action",
    "hold_action", "num_actions", "centred_reward",
]
