"""One call from buildings to a synthetic TIR sequence with ground truth: `synthesize`.

In: buildings (`citymodel.Building`, model CRS, metres) and `SynthOptions`. Out: `SynthResult`:
the `SequenceManifest` (what a package's `sequence.json` holds: recorded INS poses, nominal
mounting), the frames as a lazy `SynthFrames` (uint16 DN on indexing, float32 kelvin through
`load`, rendered on demand, identical every time), the `SynthTruth` (true poses, mounting, delay,
anomalies) and the `ThermalScene` (true temperature of any surface point).

Pure computation; writing a package and the truth file is `db.synth_files.write_synthetic_package`.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Literal

import numpy as np
import shapely

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.manifest import FrameRecord, GroundControl, SequenceManifest
from workers.pipeline.geometry.raycast import SceneMesh, build_scene_mesh
from workers.pipeline.synth.common import SynthError, rng_for
from workers.pipeline.synth.errors import ErrorOptions, InsSimulation, simulate_ins
from workers.pipeline.synth.ground import Ground, terrain_ground
from workers.pipeline.synth.occluders import OccluderOptions, Occluders, place_occluders
from workers.pipeline.synth.render import RADIOMETRY, Renderer, SensorOptions, default_camera
from workers.pipeline.synth.shapes import footprint
from workers.pipeline.synth.thermal import ThermalOptions, ThermalScene
from workers.pipeline.synth.trajectory import (
    DriveOptions,
    FlightOptions,
    LineTrajectory,
    PathTrajectory,
    TerrestrialOptions,
    camera_to_body,
    choose_cluster,
    drive_loop,
    facade_walk,
    flight_loop,
)
from workers.pipeline.synth.truth import SynthTruth
from workers.pipeline.synth.visible import RgbOptions, SynthRgb, synth_rgb

#: the true mounting errors of a hand-held camera with its GNSS/INS (`platform="terrestrial"`)
#: unless `ErrorOptions` gives them: boresight (degrees about body x, y, z), lever arm (m)
TERRESTRIAL_BORESIGHT_DEG = (0.5, -1.0, 1.0)
TERRESTRIAL_LEVER_ARM_M = (0.05, 0.1, -0.15)


@dataclass(frozen=True)
class SynthOptions:
    """Everything `synthesize` needs besides the buildings."""

    platform: Literal["drive", "flight", "terrestrial"] = "drive"
    n_frames: int = 100
    seed: int = 0
    buildings: int | tuple[str, ...] = 5  # the cluster: a count (around a central building) or ids
    frame_interval_s: float = 0.1
    t0: float = 1000.0  # time stamp of the first frame, seconds
    camera: Camera | None = None  # None: `default_camera()` (640×512, 45°, mild barrel)
    drive: DriveOptions = field(default_factory=DriveOptions)
    flight: FlightOptions = field(default_factory=FlightOptions)
    terrestrial: TerrestrialOptions = field(default_factory=TerrestrialOptions)  # a walk along one facade
    errors: ErrorOptions = field(default_factory=ErrorOptions)
    thermal: ThermalOptions = field(default_factory=ThermalOptions)
    sensor: SensorOptions = field(default_factory=SensorOptions)
    crs: str | None = None  # manifest crs; None: "EPSG:n" of the buildings' srsName, else "model"
    scene_radius_m: float | None = None  # render only buildings this close to the path; None: auto
    ground_z: float | None = None  # ground plane height; None: median base of the cluster
    # the ground follows the rendered buildings' feet (a TIN, `synth.ground`; the plane itself when
    # every foot is at one height); False, or a given `ground_z`: the plane `ground_z` everywhere
    terrain: bool = True
    n_gcps: int = 0  # ground control points (cluster building corners) with observations
    gcp_pixel_sigma: float = 0.3  # noise of the GCP image observations, pixels
    model_path: str | None = None  # recorded in the truth
    procedural: tuple[int, int] | None = None  # (n_buildings, seed) recorded when procedural
    frame_ext: str = "png"  # "png" (16-bit) or "tif"
    rgb: RgbOptions | None = None  # a second, visible-band camera on the mount (`rgb_camera`)
    occluders: OccluderOptions | None = None  # trees and cars the model lacks (`synth.occluders`)


class SynthFrames:
    """Lazy frames of a synthetic sequence: `frames[i]` -> `(H, W)` uint16 DN; `load(i)` ->
    `(H, W)` float32 kelvin (`DN · 0.01`, a `FrameSource`). Rendered on demand, deterministic;
    picklable (the ray-casting scene is rebuilt in the receiving process)."""

    def __init__(self, renderer: Renderer, poses: Sequence) -> None:
        self.renderer = renderer
        self.poses = tuple(poses)
        self._cache: tuple[int, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.poses)

    def __getitem__(self, index: int) -> np.ndarray:
        i = int(index)
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {index} out of range (0..{len(self) - 1})")
        i %= len(self)
        if self._cache is None or self._cache[0] != i:
            self._cache = (i, self.renderer.frame_dn(self.poses[i], i))
        return self._cache[1]

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(len(self)):
            yield self[i]

    def load(self, index: int) -> np.ndarray:
        """Frame `index` as float32 kelvin, exactly what a reader of the written package returns."""
        return RADIOMETRY.physical(self[index])

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_cache"] = None
        return state


@dataclass(frozen=True, eq=False)
class SynthResult:
    """Output of `synthesize` (see the module docstring). `buildings` are the rendered ones."""

    manifest: SequenceManifest
    frames: SynthFrames
    truth: SynthTruth
    thermal: ThermalScene
    mesh: SceneMesh
    buildings: tuple[Building, ...]
    ins: InsSimulation
    renderer: Renderer
    rgb: SynthRgb | None = None  # the RGB camera when `SynthOptions.rgb` asks for one


def _manifest_crs(buildings: Sequence[Building], crs: str | None) -> str:
    """The manifest's `crs`: as given, else `EPSG:<horizontal code>` of the buildings' srsName
    (URNs resolved by `workers.pipeline.geometry.crs`), else `"model"` (positions in model coordinates)."""
    if crs:
        return crs
    srs = next((b.srs_name for b in buildings if b.srs_name), None)
    if srs:
        from workers.pipeline.geometry.crs import UnknownCRSError, horizontal_epsg

        try:
            code = horizontal_epsg(srs)
        except (UnknownCRSError, ValueError):
            code = None
        if code:
            return f"EPSG:{code}"
    return "model"


def _scene_buildings(
    buildings: Sequence[Building], loop: np.ndarray, radius: float, keep: set[int]
) -> list[int]:
    """Indices of the buildings within `radius` of the loop (the cluster always kept)."""
    ring = shapely.LinearRing(loop)
    return [i for i, b in enumerate(buildings) if i in keep or ring.distance(footprint(b)) <= radius]


def _gcps(
    buildings: Sequence[Building], renderer: Renderer, poses: Sequence, n: int, sigma: float, seed: int
) -> GroundControl | None:
    """Up to `n` GCPs among the cluster's building vertices that some frame sees (true poses),
    with their image observations (+ Gaussian pixel noise `sigma`) in every frame that sees them;
    None when no frame sees any."""
    if n <= 0:
        return None
    from workers.pipeline.geometry.raycast import RayCaster

    coords = [r.coords for b in buildings for p in b.iter_polygons() for r in p.rings]
    pts = np.unique(np.round(np.concatenate(coords), 3), axis=0)
    caster = RayCaster(renderer.mesh)
    cam = renderer.camera
    seen = np.zeros((len(poses), len(pts)), bool)
    uvs = np.zeros((len(poses), len(pts), 2))
    for k, pose in enumerate(poses):
        uv, depth = pose.project(cam, pts)
        ok = (depth > 0) & cam.in_image(uv, margin=2.0)
        if np.any(ok):
            ok[ok] = caster.visible(pts[ok], pose.center, tolerance_m=0.1)
        seen[k], uvs[k] = ok, uv
    rng = rng_for(seed, "gcps")
    cand = np.flatnonzero(seen.any(axis=0))
    if len(cand) == 0:
        return None
    pick = np.sort(rng.choice(cand, size=min(n, len(cand)), replace=False)) if len(cand) else cand
    points = {f"G{j + 1}": (pts[i], 0.01) for j, i in enumerate(pick)}
    obs = [
        (k, f"G{j + 1}", uvs[k, i] + sigma * rng.standard_normal(2))
        for k in range(len(poses))
        for j, i in enumerate(pick)
        if seen[k, i]
    ]
    return GroundControl(points=points, observations=tuple(obs))


def _trajectory(
    blds: Sequence[Building], cluster: list[int], ground_z: float, o: SynthOptions
) -> tuple[PathTrajectory | LineTrajectory, np.ndarray, list[int], list[int]]:
    """The platform's true trajectory, the nominal mounting `(3, 3)`, the indices of the buildings
    rendered (near the path) and the final cluster (a drive loop may add buildings to it)."""
    if o.platform == "terrestrial":
        t = o.terrestrial
        duration = o.frame_interval_s * max(o.n_frames - 1, 1)
        start, direction = facade_walk(blds, cluster, t, duration)
        z = ground_z + t.height_m
        walk = LineTrajectory(start, direction, z, t.speed_mps, t0=o.t0, sway_deg=t.sway_deg, seed=o.seed)
        path = shapely.LineString([start, start + t.speed_mps * duration * direction])
        radius = o.scene_radius_m if o.scene_radius_m is not None else 150.0
        keep = [i for i, b in enumerate(blds) if i in cluster or path.distance(footprint(b)) <= radius]
        return walk, camera_to_body(t.look_forward_deg, t.look_up_deg), keep, cluster
    if o.platform == "drive":
        loop, cluster = drive_loop(blds, cluster, o.drive)
        height, speed, bank, sway = o.drive.height_m, o.drive.speed_mps, False, o.drive.sway_deg
        radius = o.scene_radius_m if o.scene_radius_m is not None else 150.0
    else:
        if not 20.0 <= o.flight.height_m <= 2000.0:
            raise SynthError(f"flight height_m must be 20..2000 m, got {o.flight.height_m}")
        loop = flight_loop(blds, cluster, o.flight)
        height, speed, bank, sway = o.flight.height_m, o.flight.speed_mps, True, o.flight.sway_deg
        reach = o.flight.height_m / np.tan(np.radians(o.flight.look_down_deg))
        radius = o.scene_radius_m if o.scene_radius_m is not None else 2.5 * reach
    rng = rng_for(o.seed, "trajectory")
    traj = PathTrajectory(
        loop, ground_z + height, speed, start_m=float(rng.uniform(0, 1e6)), t0=o.t0, bank=bank,
        sway_deg=sway, seed=o.seed,
    )  # fmt: skip
    if o.platform == "drive":
        M = camera_to_body(o.drive.look_forward_deg, o.drive.look_up_deg)
    else:
        M = camera_to_body(0.0, -(o.flight.look_down_deg - traj.mean_bank_deg))
    return traj, M, _scene_buildings(blds, loop, radius, set(cluster)), cluster


def _occluders(
    traj: PathTrajectory | LineTrajectory, scene: Sequence[Building], ground: Ground, o: SynthOptions
) -> Occluders | None:
    """Trees and cars the model lacks (`o.occluders`; None when not asked for): along a drive's
    loop or a walk's line, scattered around a flight's loop."""
    if o.occluders is None:
        return None
    if isinstance(traj, PathTrajectory):
        path = np.vstack([traj.loop[:, :2], traj.loop[:1, :2]])  # closed
    else:
        length = traj.speed * o.frame_interval_s * max(o.n_frames - 1, 1)
        path = np.stack([traj.start[:2], traj.start[:2] + length * traj.direction[:2]])
    fps = [footprint(b) for b in scene]
    height = None if ground.flat else ground.height
    drive = o.platform != "flight"
    return place_occluders(path, fps, ground.z, o.occluders, o.seed, drive=drive, height=height)


def synthesize(buildings: Sequence[Building], options: SynthOptions | None = None) -> SynthResult:
    """Build a synthetic sequence of `buildings` (model CRS, metres).

    Steps: choose the cluster (`options.buildings`), the ground plane (median base of the
    cluster; the trajectory's heights count from it), the closed drive/flight loop and its
    `PathTrajectory`; keep the buildings near the loop as the rendered scene (`SceneMesh`,
    `ThermalScene` from `options.seed`) on its ground (`terrain_ground`: a TIN through the
    scene's wall feet, unless `options.terrain` is off or `options.ground_z` given); stamp
    `n_frames` frames every `frame_interval_s` from `t0`; run the GNSS/INS error model (recorded
    INS at the stamps, true poses at `stamp − δ` with the true mounting); add GCPs if asked.
    Nothing is rendered here: `result.frames` renders on access. Raises `SynthError` naming the
    bad option or input.
    """
    o = options or SynthOptions()
    blds = list(buildings)
    if not blds:
        raise SynthError("buildings: none given")
    if o.n_frames < 1:
        raise SynthError(f"n_frames must be >= 1, got {o.n_frames}")
    if o.frame_interval_s <= 0:
        raise SynthError(f"frame_interval_s must be positive, got {o.frame_interval_s}")
    if o.platform not in ("drive", "flight", "terrestrial"):
        raise SynthError(f"platform must be 'drive', 'flight' or 'terrestrial', got {o.platform!r}")
    cluster = choose_cluster(blds, o.buildings if isinstance(o.buildings, int) else list(o.buildings), o.seed)
    ground_z = o.ground_z
    if ground_z is None:
        ground_z = float(np.median([blds[i].bounds()[0][2] for i in cluster]))
    traj, M, keep, cluster = _trajectory(blds, cluster, float(ground_z), o)
    scene = [blds[i] for i in keep]
    mesh = build_scene_mesh(scene)
    thermal = ThermalScene(scene, mesh.polygon_ids, seed=o.seed, options=o.thermal)
    camera = o.camera or default_camera()
    terrain = o.terrain and o.ground_z is None
    ground = terrain_ground(scene, float(ground_z)) if terrain else Ground(float(ground_z))
    occluders = _occluders(traj, scene, ground, o)
    renderer = Renderer(mesh, thermal, camera, ground, o.sensor, seed=o.seed, occluders=occluders)

    times = o.t0 + o.frame_interval_s * np.arange(o.n_frames)
    errors = o.errors
    if o.platform == "terrestrial":  # a hand-held camera with its GNSS/INS: a short lever arm
        errors = replace(
            errors,
            boresight_deg=errors.boresight_deg or TERRESTRIAL_BORESIGHT_DEG,
            lever_arm_m=errors.lever_arm_m or TERRESTRIAL_LEVER_ARM_M,
        )
    ins = simulate_ins(traj.state, times, M, o.platform, errors, o.seed)
    ext = o.frame_ext.lower().lstrip(".")
    if ext not in ("png", "tif"):
        raise SynthError(f"frame_ext must be 'png' or 'tif', got {o.frame_ext!r}")
    frames = tuple(
        FrameRecord(
            index=i,
            file=f"frames/{i:06d}.{ext}",
            time=float(times[i]),
            position=ins.frame_positions[i],
            attitude_deg=ins.frame_attitudes[i],
        )
        for i in range(o.n_frames)
    )
    gcps = _gcps([blds[i] for i in cluster], renderer, ins.poses, o.n_gcps, o.gcp_pixel_sigma, o.seed)
    rgb = None
    if o.rgb is not None:
        rgb = synth_rgb(renderer, list(ins.poses), ins.true_mounting, times - ins.time_delay_s, o.rgb, o.seed)
    manifest = SequenceManifest(
        platform=o.platform,
        crs=_manifest_crs(scene, o.crs),
        camera=camera,
        radiometry=RADIOMETRY,
        mounting=ins.manifest_mounting,
        frames=frames,
        heading_reference="grid",
        accuracy=ins.accuracy,
        imu=ins.imu,
        gcps=gcps,
        rgb=None if rgb is None else rgb.second_camera,
    )
    truth = SynthTruth(
        seed=o.seed,
        platform=o.platform,
        crs=manifest.crs,
        model_path=o.model_path,
        procedural={"n_buildings": o.procedural[0], "seed": o.procedural[1]} if o.procedural else None,
        buildings=tuple(b.id for b in scene),
        cluster=tuple(blds[i].id for i in cluster),
        ground_z=float(ground_z),
        frame_times=times,
        exposure_times=times - ins.time_delay_s,
        poses=ins.poses,
        true_mounting=ins.true_mounting,
        manifest_mounting=ins.manifest_mounting,
        time_delay_s=ins.time_delay_s,
        position_error=ins.position_error,
        attitude_error=ins.attitude_error,
        anomalies=thermal.anomalies,
        windows=thermal.windows,
        occluders=() if occluders is None else occluders.items,
        ground=None if ground.flat else ground,
        thermal=o.thermal,
        sensor=o.sensor,
        errors=asdict(errors),
    )
    return SynthResult(
        manifest=manifest,
        frames=SynthFrames(renderer, ins.poses),
        truth=truth,
        thermal=thermal,
        mesh=mesh,
        buildings=tuple(scene),
        ins=ins,
        renderer=renderer,
        rgb=rgb,
    )
