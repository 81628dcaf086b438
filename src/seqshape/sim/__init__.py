"""seqshape.sim: synthetic LiDAR tracks of vehicles and camera + LiDAR scenes.

* `sensors`: LiDAR presets (`LidarConfig`, `get_sensor`, `ray_directions`); a sensor owns its
  sweep directions and window, range limits, range noise and dropout;
* `raycast`: the one raycast core (Embree, exact float64 ranges): a vehicle along a track
  (`scan_vehicle`, `scan_track`), rays from one origin at posed meshes (`cast_posed`,
  `scene_hits`) and the bare `full_sweep` reference;
* `kinematics`, `trajectories`, `traffic`: the bicycle model and footprints, the crossing
  placement (`sample_trajectory`) and CSV logs (`read_trajectory_csv`), the traffic placement;
* `real`: the realistic scan and crop of the ``real`` preset;
* `generate` (with `_worker`, the per-track work): whole datasets (`GenerateConfig`,
  `PRESETS`, `generate_dataset`);
* `scenes`, `render`, `scene_writer`, `degrade`: camera + LiDAR scenes in the KITTI layout
  with exact amodal ground truth and degraded 2D instances.

Long runs (`generate_dataset`, `scene_writer.generate_scenes`) go through `seqshape._runner`
(settings check, resume, shards, worker pool).
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
