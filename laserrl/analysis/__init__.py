"""Analysis of the cavity beyond single episodes: reward landscapes swept with the state
carried over (bistability, hysteresis) and angle paths replayed through the physics."""
from laserrl.analysis.landscape import (StepSettings, Sweep, cold_landscape, interval_width, intervals,
                                        settle, sweep)
from laserrl.analysis.paths import PathResult, follow_paths, full_angles, straight_path

__all__ = [
    "StepSettings", "Sweep", "cold_landscape", "interval_width", "intervals", "settle", "sweep",
    "PathResult", "follow_paths", "full_angles", "straight_path",
]
