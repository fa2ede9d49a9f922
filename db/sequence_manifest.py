"""Parse and check `sequence.json`, `imu.csv` and `gcps.json` (`citytherm-sequence/1`).

In: the decoded JSON object of `sequence.json` and the package root folder (to read the optional
`imu` CSV and `gcps` JSON it names, and to check that frame files exist).
Out: a `workers.pipeline.geometry.manifest.SequenceManifest` (positions still in the manifest's `crs`).

Every refusal raises `PackageError` (a `ValueError`) whose `.field` names the offending field
(`frames[3].position[1]`, `mounting.camera_to_body`) or file (`frames/000003.png`,
`imu.csv:12`) and whose message starts with that name. `manifest_to_dict` is the inverse.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from db.sequence_conditions import parse_conditions
from db.sequence_fields import (  # the field readers, shared with db.sequence_rgb
    HEADING_REFERENCES,
    IMU_HEADER,
    PLATFORMS,
    PackageError,
    _accuracy,
    _camera,
    _choice,
    _existing_file,
    _frames,
    _get,
    _mounting,
    _number,
    _radiometry,
    _vector,
    safe_relative,
)
from workers.pipeline.geometry.crs import UnknownCRSError, resolve_crs
from workers.pipeline.geometry.manifest import (
    FORMAT,
    GroundControl,
    ImuSamples,
    SecondCamera,
    SequenceManifest,
)


def parse_imu_csv(path: Path, name: str = "imu.csv") -> ImuSamples:
    """`time,x,y,z,roll,pitch,heading` CSV -> `ImuSamples`; errors name `name:line`."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise PackageError(name, f"unreadable: {exc}") from exc
    numbered = [(k + 1, r) for k, r in enumerate(rows) if any(c.strip() for c in r)]  # 1-based lines
    if not numbered or tuple(c.strip().lower() for c in numbered[0][1]) != IMU_HEADER:
        raise PackageError(name, f"header must be {','.join(IMU_HEADER)!r}")
    if len(numbered) < 2:
        raise PackageError(name, "no samples")
    data = np.empty((len(numbered) - 1, 7))
    for j, (lineno, row) in enumerate(numbered[1:]):
        line = f"{name}:{lineno}"
        if len(row) != 7:
            raise PackageError(line, f"expected 7 values, got {len(row)}")
        for k, cell in enumerate(row):
            try:
                v = float(cell)
            except ValueError:
                raise PackageError(f"{line}.{IMU_HEADER[k]}", f"not a number: {cell!r}") from None
            if not math.isfinite(v):
                raise PackageError(f"{line}.{IMU_HEADER[k]}", f"non-finite number {cell!r}")
            data[j, k] = v
    bad = np.nonzero(np.diff(data[:, 0]) <= 0)[0]
    if len(bad):
        raise PackageError(f"{name}:{numbered[bad[0] + 2][0]}.time", "times must increase")
    return ImuSamples(time=data[:, 0], position=data[:, 1:4], attitude_deg=data[:, 4:7])


def parse_gcps(path: Path, n_frames: int, name: str = "gcps.json") -> GroundControl:
    """`gcps.json` -> `GroundControl`; observations must name known points and frames."""
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PackageError(name, f"unreadable JSON: {exc}") from exc
    pts_raw = _get(d, "points", name)
    if not isinstance(pts_raw, list):
        raise PackageError(f"{name}.points", "expected an array")
    points: dict[str, tuple[np.ndarray, float | None]] = {}
    for i, p in enumerate(pts_raw):
        f = f"{name}.points[{i}]"
        pid = _get(p, "id", f)
        if not isinstance(pid, str) or pid in points:
            raise PackageError(f"{f}.id", f"expected a unique string id, got {pid!r}")
        sigma = p.get("sigma_m")
        s = None if sigma is None else _number(sigma, f"{f}.sigma_m")
        if s is not None and s <= 0:
            raise PackageError(f"{f}.sigma_m", "must be positive")
        points[pid] = (_vector(_get(p, "xyz", f), 3, f"{f}.xyz"), s)
    obs_raw = d.get("observations", [])
    if not isinstance(obs_raw, list):
        raise PackageError(f"{name}.observations", "expected an array")
    obs = []
    for i, o in enumerate(obs_raw):
        f = f"{name}.observations[{i}]"
        fr = _get(o, "frame", f)
        if isinstance(fr, bool) or not isinstance(fr, int) or not 0 <= fr < n_frames:
            raise PackageError(f"{f}.frame", f"expected a frame index in 0..{n_frames - 1}, got {fr!r}")
        pid = _get(o, "id", f)
        if pid not in points:
            raise PackageError(f"{f}.id", f"unknown point id {pid!r}")
        obs.append((fr, pid, _vector(_get(o, "uv", f), 2, f"{f}.uv")))
    return GroundControl(points=points, observations=tuple(obs))


def parse_manifest(d: Any, root: Path | None = None) -> SequenceManifest:
    """Decoded `sequence.json` -> `SequenceManifest`.

    With `root` (the package folder), frame files must exist and `imu` / `gcps` are read;
    without it those files are not touched (`imu` / `gcps` then stay None).
    """
    if not isinstance(d, Mapping):
        raise PackageError("sequence.json", "expected a JSON object")
    fmt = d.get("format")
    if fmt != FORMAT:
        raise PackageError("format", f"unknown format {fmt!r} (expected {FORMAT!r})")
    crs = _get(d, "crs", "")
    if not isinstance(crs, str):
        raise PackageError("crs", f"expected a CRS name, got {crs!r}")
    if crs.strip().lower() != "model":
        try:
            resolve_crs(crs)
        except UnknownCRSError as exc:
            raise PackageError("crs", str(exc)) from exc
    att = d.get("attitude") or {}
    if not isinstance(att, Mapping):
        raise PackageError("attitude", f"expected a JSON object, got {att!r}")
    heading_reference = _choice(
        att.get("heading_reference", "grid"), HEADING_REFERENCES, "attitude.heading_reference"
    )
    frames = _frames(_get(d, "frames", ""), root)
    imu = gcps = None
    if root is not None and d.get("imu") is not None:
        rel = safe_relative(d["imu"], "imu")
        imu = parse_imu_csv(_existing_file(root, rel, "imu"), rel)
    if root is not None and d.get("gcps") is not None:
        rel = safe_relative(d["gcps"], "gcps")
        gcps = parse_gcps(_existing_file(root, rel, "gcps"), len(frames), rel)
    vo = d.get("vertical_offset_m")
    return SequenceManifest(
        platform=_choice(_get(d, "platform", ""), PLATFORMS, "platform"),
        crs=crs,
        camera=_camera(_get(d, "camera", "")),
        radiometry=_radiometry(_get(d, "radiometry", "")),
        mounting=_mounting(_get(d, "mounting", "")),
        frames=frames,
        heading_reference=heading_reference,
        vertical_offset_m=0.0 if vo is None else _number(vo, "vertical_offset_m"),
        accuracy=None if d.get("accuracy") is None else _accuracy(d["accuracy"]),
        imu=imu,
        gcps=gcps,
        conditions=None if d.get("conditions") is None else parse_conditions(d["conditions"], PackageError),
        rgb=None if d.get("rgb_camera") is None else _rgb_camera(d["rgb_camera"], root),
    )


def _rgb_camera(d: Any, root: Path | None) -> SecondCamera:
    """The optional `rgb_camera` section (`db.sequence_rgb.parse_rgb_camera`)."""
    from db.sequence_rgb import parse_rgb_camera  # it builds on this module's field readers

    return parse_rgb_camera(d, root)


# -- writing -------------------------------------------------------------------------------------
def manifest_to_dict(
    manifest: SequenceManifest, imu_file: str = "imu.csv", gcps_file: str = "gcps.json"
) -> dict[str, Any]:
    """`SequenceManifest` -> the JSON object of `sequence.json` (plain lists and floats).

    `imu` / `gcps` name `imu_file` / `gcps_file` when the manifest carries them.
    """
    m = manifest
    d: dict[str, Any] = {
        "format": FORMAT,
        "platform": m.platform,
        "crs": m.crs,
        "vertical_offset_m": float(m.vertical_offset_m),
        "camera": m.camera.to_dict(),
        "radiometry": {
            "unit": m.radiometry.unit,
            "scale": float(m.radiometry.scale),
            "offset": float(m.radiometry.offset),
        },
        "mounting": {
            "camera_to_body": np.asarray(m.mounting.camera_to_body, dtype=float).reshape(3, 3).tolist(),
            "boresight_deg": np.asarray(m.mounting.boresight_deg, dtype=float).reshape(3).tolist(),
            "lever_arm_m": np.asarray(m.mounting.lever_arm_m, dtype=float).reshape(3).tolist(),
        },
        "attitude": {"heading_reference": m.heading_reference},
    }
    if m.accuracy is not None:
        d["accuracy"] = {
            "position_m": np.asarray(m.accuracy.position_m, dtype=float).reshape(3).tolist(),
            "attitude_deg": np.asarray(m.accuracy.attitude_deg, dtype=float).reshape(3).tolist(),
        }
    d["frames"] = [
        {
            "file": f.file,
            "time": float(f.time),
            "position": np.asarray(f.position, dtype=float).reshape(3).tolist(),
            "attitude_deg": np.asarray(f.attitude_deg, dtype=float).reshape(3).tolist(),
        }
        for f in m.frames
    ]
    if m.conditions is not None and m.conditions.to_dict():
        d["conditions"] = m.conditions.to_dict()
    if m.rgb is not None:
        from db.sequence_rgb import rgb_camera_to_dict

        d["rgb_camera"] = rgb_camera_to_dict(m.rgb)
    if m.imu is not None:
        d["imu"] = imu_file
    if m.gcps is not None:
        d["gcps"] = gcps_file
    return d


def gcps_to_dict(gcps: GroundControl) -> dict[str, Any]:
    """`GroundControl` -> the JSON object of `gcps.json`."""
    points = []
    for pid, (xyz, sigma) in gcps.points.items():
        p: dict[str, Any] = {"id": pid, "xyz": np.asarray(xyz, dtype=float).reshape(3).tolist()}
        if sigma is not None:
            p["sigma_m"] = float(sigma)
        points.append(p)
    obs = [
        {"frame": int(fr), "id": pid, "uv": np.asarray(uv, dtype=float).reshape(2).tolist()}
        for fr, pid, uv in gcps.observations
    ]
    return {"points": points, "observations": obs}


def write_imu_csv(path: Path, imu: ImuSamples) -> None:
    """`ImuSamples` -> `imu.csv` with the spec's header (full float precision)."""
    data = np.column_stack(
        [
            np.asarray(imu.time, float),
            np.asarray(imu.position, float).reshape(-1, 3),
            np.asarray(imu.attitude_deg, float).reshape(-1, 3),
        ]
    )
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(IMU_HEADER)
        for row in data:
            w.writerow([repr(float(v)) for v in row])
