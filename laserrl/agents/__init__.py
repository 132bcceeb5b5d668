"""Double DQN agent built from TorchRL's parts."""
from laserrl.agents.qnet import FieldQNet

__all__ = ["FieldQNet"]
