"""Synthetic TIR sequences with ground truth (`citytherm synth`).

In: CityGML buildings (`citymodel.Building`, model CRS, metres) or a procedural block.
Out: a sequence package (`docs/sequence-format.md`) rendered by ray casting, with a ground-truth
file next to it (`docs/synth-truth.md`): true camera poses, true mounting and delay, anomalies.

Public API (everything below is importable from `workers.pipeline.synth`):

- `synthesize(buildings, SynthOptions(...)) -> SynthResult` — one call, pure, lazy frames:
  `result.manifest` (`SequenceManifest`: recorded INS poses, nominal mounting, imu, gcps),
  `result.frames` (`SynthFrames`: `frames[i]` uint16 DN `(H, W)`, `frames.load(i)` float32 K,
  a picklable `FrameSource`), `result.truth` (`SynthTruth`: `poses[i]` true `Pose`,
  `true_mounting`, `time_delay_s`, `anomalies`, ...), `result.thermal` (`ThermalScene`),
  `result.mesh` (`SceneMesh`), `result.buildings` (the rendered ones), `result.renderer`,
  `result.ins` (`InsSimulation`: recorded vs true INS states, per-frame errors).
- `thermal_scene_for_truth(truth, buildings)`: the exact temperature field of a truth's scene.
  Its files (`write_synthetic_package(result, out_dir, truth_path=None) -> Path`,
  `load_truth(path)`, `save_truth(truth, path)`, `load_buildings(truth)`) are in `db.synth_files`.
- `ThermalScene(buildings, polygon_ids=None, seed=0, options=ThermalOptions())`:
  `temperature(points (N,3), polygon_index (N,)) -> (N,) float32 K`,
  `surface_temperature(polygon_id_or_index, points (N,3)) -> (N,) K`,
  `ground_temperature(points)`, `sky_temperature(directions)`, `anomalies`.
- `Renderer(mesh, thermal, camera, ground_z, SensorOptions(), seed)` (`ground_z`: a plane's height or a
  `synth.ground.Ground` terrain, `terrain_ground(buildings, z0)`): `radiance(pose)` (ideal K),
  `frame(pose, index)` (sensor effects), `frame_dn`, `labels(pose)` (polygon index per pixel).
- `procedural_block(n_buildings, seed) -> list[Building]`; `default_camera()`.
- `SynthOptions(occluders=OccluderOptions())`: street trees and parked cars the model lacks,
  rendered (label `OCCLUDER`) and listed in `truth.occluders` (`place_occluders`, `Occluders`).
- Options: `SynthOptions`, `DriveOptions`, `FlightOptions`, `ErrorOptions`, `ThermalOptions`,
  `SensorOptions`, `RgbOptions` (`SynthOptions(rgb=RgbOptions())`: a second, visible-band camera;
  `result.rgb` is a `SynthRgb`: lazy `(H, W, 3)` uint8 `frames`, `true_poses`, `recorded_poses`,
  the manifest's `second_camera`). Errors: `SynthError`.

Typical test use::

    from workers.pipeline.synth import SynthOptions, ErrorOptions, procedural_block, synthesize
    res = synthesize(procedural_block(6, seed=1), SynthOptions(n_frames=20, seed=1, buildings=3))
    img = res.frames.load(0); pose = res.truth.poses[0]; T = res.thermal.surface_temperature(pid, X)
"""

from workers.pipeline.synth.anomaly import Anomaly
from workers.pipeline.synth.common import BUNDLED_MODEL, SynthError
from workers.pipeline.synth.errors import ErrorOptions, InsSimulation, simulate_ins
from workers.pipeline.synth.occluders import OccluderOptions, Occluders, place_occluders
from workers.pipeline.synth.procedural import gable_house, procedural_block
from workers.pipeline.synth.render import (
    GROUND,
    OCCLUDER,
    RADIOMETRY,
    SKY,
    Renderer,
    SensorOptions,
    default_camera,
)
from workers.pipeline.synth.scene import SynthFrames, SynthOptions, SynthResult, synthesize
from workers.pipeline.synth.thermal import ThermalOptions, ThermalScene
from workers.pipeline.synth.trajectory import DriveOptions, FlightOptions, PathTrajectory
from workers.pipeline.synth.truth import SynthTruth, thermal_scene_for_truth
from workers.pipeline.synth.visible import RgbOptions, RgbRenderer, SynthRgb

__all__ = [
    "BUNDLED_MODEL",
    "GROUND",
    "OCCLUDER",
    "RADIOMETRY",
    "SKY",
    "Anomaly",
    "DriveOptions",
    "ErrorOptions",
    "FlightOptions",
    "InsSimulation",
    "OccluderOptions",
    "Occluders",
    "PathTrajectory",
    "Renderer",
    "RgbOptions",
    "RgbRenderer",
    "SensorOptions",
    "SynthError",
    "SynthFrames",
    "SynthOptions",
    "SynthResult",
    "SynthRgb",
    "SynthTruth",
    "ThermalOptions",
    "ThermalScene",
    "default_camera",
    "gable_house",
    "place_occluders",
    "procedural_block",
    "simulate_ins",
    "synthesize",
    "thermal_scene_for_truth",
]
