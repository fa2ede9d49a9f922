"""Ground truth of a synthetic sequence (`citytherm-synth-truth/1`), documented in
`docs/synth-truth.md`.

In: what `synthesize` knows (true poses, mounting, delay, planted leaks with their half-maximum
outlines, the walls' window rectangles, the terrain, options). Out: a
`SynthTruth` and its JSON form (`to_dict` / `from_dict`; files via `db.synth_files`). Poses are
`R_wc` (camera to world, rows) and `C` (world, model CRS, metres).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.manifest import Mounting
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.options import OptionsError, options_from_dict
from workers.pipeline.synth.anomaly import Anomaly, Window
from workers.pipeline.synth.common import SynthError
from workers.pipeline.synth.ground import Ground
from workers.pipeline.synth.render import SensorOptions
from workers.pipeline.synth.thermal import ThermalOptions, ThermalScene

TRUTH_FORMAT = "citytherm-synth-truth/1"


def _mounting_to_dict(m: Mounting) -> dict[str, Any]:
    return {
        "camera_to_body": np.asarray(m.camera_to_body, float).reshape(3, 3).tolist(),
        "boresight_deg": np.asarray(m.boresight_deg, float).reshape(3).tolist(),
        "lever_arm_m": np.asarray(m.lever_arm_m, float).reshape(3).tolist(),
    }


def _mounting_from_dict(d: dict[str, Any]) -> Mounting:
    return Mounting(
        np.asarray(d["camera_to_body"], float).reshape(3, 3),
        np.asarray(d["boresight_deg"], float).reshape(3),
        np.asarray(d["lever_arm_m"], float).reshape(3),
    )


@dataclass(frozen=True, eq=False)
class SynthTruth:
    """Everything true about a synthetic sequence.

    Attributes:
        seed: the scene seed (thermal field, trajectory, errors, noise).
        platform: `"drive"` or `"flight"`.
        crs: the manifest's `crs`.
        model_path: CityGML file the buildings came from (None: procedural or in memory).
        procedural: `{"n_buildings", "seed"}` when the buildings came from `procedural_block`.
        buildings: ids of all rendered buildings (the scene).
        cluster: ids of the buildings the trajectory goes around.
        ground_z: height of the ground plane, metres (with a terrain: beyond its outer square,
            and the base of the trajectory's heights).
        frame_times: `(F,)` stamps as in the manifest, seconds.
        exposure_times: `(F,)` true exposure times `frame_times − time_delay_s`.
        poses: true camera pose per frame (`R_world_from_cam`, `center`).
        true_mounting: the platform's real mounting (boresight, lever arm).
        manifest_mounting: the mounting the manifest states.
        time_delay_s: true camera-to-INS delay δ.
        position_error: `(F, 3)` recorded minus true INS position at the stamps, metres.
        attitude_error: `(F, 3)` recorded minus true INS attitude at the stamps, degrees.
        anomalies: planted leaks (centre, σ, ΔT, half-maximum outline and area).
        thermal: options of the temperature field.
        sensor: sensor effects.
        errors: the error-model options as given (`asdict` form).
        package: package folder the truth belongs to (relative to the truth file or absolute).
        windows: the window rectangles of every wall of the scene (`ThermalScene.windows`;
            empty in truth files written before windows were recorded).
        occluders: the trees and cars rendered that the model lacks (`synth.occluders`: kind,
            centre, size); empty without `SynthOptions.occluders`.
        ground: the terrain (`synth.ground.Ground`: a TIN through the buildings' feet inside the
            plane `ground_z`); None: the plane `ground_z` everywhere.
    """

    seed: int
    platform: str
    crs: str
    model_path: str | None
    procedural: dict[str, int] | None
    buildings: tuple[str, ...]
    cluster: tuple[str, ...]
    ground_z: float
    frame_times: np.ndarray
    exposure_times: np.ndarray
    poses: tuple[Pose, ...]
    true_mounting: Mounting
    manifest_mounting: Mounting
    time_delay_s: float
    position_error: np.ndarray
    attitude_error: np.ndarray
    anomalies: tuple[Anomaly, ...]
    thermal: ThermalOptions
    sensor: SensorOptions
    errors: dict[str, Any]
    package: str | None = None
    windows: tuple[Window, ...] = ()
    occluders: tuple[dict, ...] = ()
    ground: Ground | None = None

    def ground_height(self, xy: np.ndarray) -> np.ndarray:
        """Height `(N,)` m of the scene's ground under world points `xy` `(N, 2)` (or `(N, 3)`)."""
        if self.ground is None:
            return np.full(len(xy), float(self.ground_z))
        return self.ground.height(xy)

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of the truth file."""
        return {
            "format": TRUTH_FORMAT,
            "seed": self.seed,
            "platform": self.platform,
            "crs": self.crs,
            "model_path": self.model_path,
            "procedural": self.procedural,
            "package": self.package,
            "buildings": list(self.buildings),
            "cluster": list(self.cluster),
            "ground_z": self.ground_z,
            "time_delay_s": self.time_delay_s,
            "true_mounting": _mounting_to_dict(self.true_mounting),
            "manifest_mounting": _mounting_to_dict(self.manifest_mounting),
            "frames": [
                {
                    "index": i,
                    "time": float(self.frame_times[i]),
                    "exposure_time": float(self.exposure_times[i]),
                    "R_wc": p.R_world_from_cam.tolist(),
                    "C": p.center.tolist(),
                    "position_error_m": self.position_error[i].tolist(),
                    "attitude_error_deg": self.attitude_error[i].tolist(),
                }
                for i, p in enumerate(self.poses)
            ],
            "anomalies": [a.to_dict() for a in self.anomalies],
            "windows": [w.to_dict() for w in self.windows],
            "occluders": [dict(o) for o in self.occluders],
            "thermal": asdict(self.thermal),
            "sensor": asdict(self.sensor),
            "errors": dict(self.errors),
            **({} if self.ground is None or self.ground.flat else {"ground": self.ground.to_dict()}),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SynthTruth:
        """Inverse of `to_dict`; raises `SynthError` naming a missing or bad field."""
        if d.get("format") != TRUTH_FORMAT:
            raise SynthError(f"truth: format must be {TRUTH_FORMAT!r}, got {d.get('format')!r}")
        try:
            frames = d["frames"]
            return cls(
                seed=int(d["seed"]),
                platform=str(d["platform"]),
                crs=str(d["crs"]),
                model_path=d.get("model_path"),
                procedural=d.get("procedural"),
                buildings=tuple(d["buildings"]),
                cluster=tuple(d["cluster"]),
                ground_z=float(d["ground_z"]),
                frame_times=np.array([f["time"] for f in frames], float),
                exposure_times=np.array([f["exposure_time"] for f in frames], float),
                poses=tuple(Pose(np.array(f["R_wc"], float), np.array(f["C"], float)) for f in frames),
                true_mounting=_mounting_from_dict(d["true_mounting"]),
                manifest_mounting=_mounting_from_dict(d["manifest_mounting"]),
                time_delay_s=float(d["time_delay_s"]),
                position_error=np.array([f["position_error_m"] for f in frames], float).reshape(-1, 3),
                attitude_error=np.array([f["attitude_error_deg"] for f in frames], float).reshape(-1, 3),
                anomalies=tuple(Anomaly.from_dict(a) for a in d.get("anomalies", [])),
                thermal=options_from_dict(ThermalOptions, d.get("thermal"), strict=False),
                sensor=options_from_dict(SensorOptions, d.get("sensor"), strict=False),
                errors=dict(d.get("errors") or {}),
                package=d.get("package"),
                windows=tuple(Window.from_dict(w) for w in d.get("windows") or []),
                occluders=tuple(dict(o) for o in d.get("occluders") or []),
                ground=Ground.from_dict(d["ground"]) if d.get("ground") else None,
            )
        except (KeyError, TypeError, ValueError, OptionsError) as exc:
            raise SynthError(f"truth: missing or bad field ({exc})") from exc


def thermal_scene_for_truth(
    truth: SynthTruth, buildings: Sequence[Building], polygon_ids: Sequence[str] | None = None
) -> ThermalScene:
    """The temperature field that rendered the truth's frames, for `buildings` (any subset of
    the scene: a building's field depends only on the seed and itself)."""
    return ThermalScene(buildings, polygon_ids, seed=truth.seed, options=truth.thermal)
