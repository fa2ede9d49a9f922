"""Write an analytic texture scene (`texture_scene`) as real input files: a CityGML 2.0 model and
a sequence package whose manifest reproduces the given camera poses exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from db.citygml.writer import write_citygml
from db.sequence_package import write_package
from tests.unit.texture_scene import render
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.georef import attitude_from_ned_from_body
from workers.pipeline.geometry.manifest import Accuracy, FrameRecord, Mounting, Radiometry, SequenceManifest
from workers.pipeline.geometry.pose import Pose

R_WN = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])
M = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])  # camera looking forward, level
SRS = "EPSG:25832"


def write_scene(
    folder: Path,
    buildings: list[Building],
    camera: Camera,
    poses: list[Pose],
    edge_m: float = 0.15,
    accuracy: Accuracy | None = None,
) -> tuple[Path, Path]:
    """Write `folder/city.gml` and the package `folder/seq` (the manifest states `accuracy`, the
    a-priori σ of its poses, when given); returns both paths."""
    gml = folder / "city.gml"
    write_citygml(gml, buildings, srs_name=SRS)
    records = []
    for i, p in enumerate(poses):
        R_nb = R_WN.T @ p.R_world_from_cam @ M.T
        records.append(
            FrameRecord(
                index=i,
                file=f"frames/{i:06d}.png",
                time=0.1 * i,
                position=p.center.copy(),
                attitude_deg=attitude_from_ned_from_body(R_nb),
            )
        )
    manifest = SequenceManifest(
        platform="drive",
        crs="model",
        camera=camera,
        radiometry=Radiometry("K", 0.01, 0.0),
        mounting=Mounting(camera_to_body=M),
        frames=tuple(records),
        accuracy=accuracy,
    )
    pkg = write_package(folder / "seq", manifest, (render(camera, p, buildings, edge_m) for p in poses))
    return gml, pkg
