"""Protocol simulators: simulated stage controllers that speak the real serial protocols on a pty.

`GrblSim` (GRBL 1.1) and `ZaberSim` (Zaber ASCII) reuse the drivers' codecs, move with realistic
timing and inject faults on demand (see `drivers.sim.base` for the fault API). `start()` serves one on
a new pty whose `path` a driver opens like a real port; `close()` releases the thread and descriptors.
"""

from .base import Motion, SimDevice
from .grbl_sim import GrblSim
from .zaber_sim import ZaberSim

__all__ = ["GrblSim", "Motion", "SimDevice", "ZaberSim"]
