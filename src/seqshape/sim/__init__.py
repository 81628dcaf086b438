"""seqshape.sim: synthetic LiDAR tracks of vehicles.

* `sensors`: LiDAR presets (`LidarConfig`, `get_sensor`, `ray_directions`);
* `raycast`: first-hit Embree raycasting of a vehicle along a track (`scan_vehicle`,
  `scan_track`) and the bare `full_sweep` reference;
* `trajectories`: kinematic bicycle model (`sample_trajectory`) and CSV logs
  (`read_trajectory_csv`);
* `generate`: whole datasets (`GenerateConfig`, `PRESETS`, `generate_dataset`).
"""

from seqshape.sim.generate import (
    PRESETS,
    GenerateConfig,
    GenerateSummary,
    generate_dataset,
    preset_config,
)
from seqshape.sim.raycast import full_sweep, scan_track, scan_vehicle
from seqshape.sim.sensors import SENSORS, LidarConfig, get_sensor, ray_directions
from seqshape.sim.trajectories import (
    MANOEUVRES,
    Trajectory,
    read_trajectory_csv,
    sample_trajectory,
)

__all__ = [
    "MANOEUVRES",
    "PRESETS",
    "SENSORS",
    "GenerateConfig",
    "GenerateSummary",
    "LidarConfig",
    "Trajectory",
    "full_sweep",
    "generate_dataset",
    "get_sensor",
    "preset_config",
    "ray_directions",
    "read_trajectory_csv",
    "sample_trajectory",
    "scan_track",
    "scan_vehicle",
]
