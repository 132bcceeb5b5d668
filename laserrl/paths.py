"""Files that ship inside the package: the Hydra configs and the reference solutions."""
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent

#: The Hydra config folder of every entry point (``laserrl/conf``).
CONF_DIR = str(_PACKAGE / "conf")
#: High-accuracy reference trajectories of the cavity (see laserrl.physics.reference).
REFERENCE_DATA = _PACKAGE / "data" / "cavity_reference.npz"
