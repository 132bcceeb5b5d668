from laserrl import gym  # noqa: F401  registers the Gymnasium ids laserrl/ModeLock-*-v0
