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
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from db.sequence_conditions import parse_conditions
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.crs import UnknownCRSError, resolve_crs
from workers.pipeline.geometry.manifest import (
    FORMAT,
    Accuracy,
    FrameRecord,
    GroundControl,
    ImuSamples,
    Mounting,
    Radiometry,
    SecondCamera,
    SequenceManifest,
)

PLATFORMS = ("drive", "flight", "terrestrial")
UNITS = ("K", "degC", "counts")
HEADING_REFERENCES = ("grid", "true")
IMU_HEADER = ("time", "x", "y", "z", "roll", "pitch", "heading")
ORTHONORMAL_TOL = 1e-6


class PackageError(ValueError):
    """A sequence package that must be refused. `.field` is the offending field or file."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}")


# -- typed field access --------------------------------------------------------------------------
def _get(obj: Mapping[str, Any], key: str, path: str) -> Any:
    if not isinstance(obj, Mapping):
        raise PackageError(path, "expected a JSON object")
    if key not in obj or obj[key] is None:
        raise PackageError(f"{path}.{key}" if path else key, "missing")
    return obj[key]


def _number(value: Any, field: str) -> float:
    """A finite JSON number (bool is not a number)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PackageError(field, f"expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise PackageError(field, f"non-finite number {value!r}")
    return v


def _vector(value: Any, n: int, field: str) -> np.ndarray:
    """A JSON array of `n` finite numbers -> `(n,)` float64."""
    if not isinstance(value, list | tuple) or len(value) != n:
        raise PackageError(field, f"expected an array of {n} numbers, got {value!r}")
    return np.array([_number(v, f"{field}[{i}]") for i, v in enumerate(value)])


def _num_or_vector(value: Any, field: str) -> np.ndarray:
    """A number or an array of 3 numbers -> `(3,)`."""
    if isinstance(value, list | tuple):
        return _vector(value, 3, field)
    return np.full(3, _number(value, field))


def _choice(value: Any, options: tuple[str, ...], field: str) -> str:
    if value not in options:
        raise PackageError(field, f"{value!r} is not one of {list(options)}")
    return str(value)


def safe_relative(name: Any, field: str) -> str:
    """A relative POSIX path inside the package (no absolute path, no `..`, no backslash)."""
    if not isinstance(name, str) or not name.strip():
        raise PackageError(field, f"expected a relative file name, got {name!r}")
    if "\\" in name or name.startswith("/") or (len(name) > 1 and name[1] == ":"):
        raise PackageError(field, f"{name!r} must be a relative path inside the package")
    parts = PurePosixPath(name).parts
    if ".." in parts:
        raise PackageError(field, f"{name!r} must not contain '..'")
    return str(PurePosixPath(*[p for p in parts if p != "."]))


def _existing_file(root: Path, name: str, field: str) -> Path:
    """`root / name`, checked to be a regular file inside `root` (symlinks out are refused)."""
    rel = safe_relative(name, field)
    p = root / rel
    try:
        real = p.resolve(strict=True)
    except (FileNotFoundError, OSError):
        raise PackageError(rel, f"file not found (named by {field})") from None
    if not real.is_relative_to(root.resolve()):
        raise PackageError(rel, "resolves outside the package")
    if not real.is_file():
        raise PackageError(rel, "not a regular file")
    return p


# -- sections ------------------------------------------------------------------------------------
def _camera(d: Any, path: str = "camera") -> Camera:
    if not isinstance(d, Mapping):
        raise PackageError(path, "expected a JSON object")
    model = d.get("model", "OPENCV")
    if model != "OPENCV":
        raise PackageError(f"{path}.model", f"{model!r} is not 'OPENCV'")
    kw: dict[str, Any] = {}
    for k in ("width", "height"):
        v = _number(_get(d, k, path), f"{path}.{k}")
        if v != int(v) or v < 1:
            raise PackageError(f"{path}.{k}", f"expected a positive integer, got {d[k]!r}")
        kw[k] = int(v)
    for k in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"):
        kw[k] = _number(_get(d, k, path), f"{path}.{k}")
    for k in ("fx", "fy"):
        if kw[k] <= 0:
            raise PackageError(f"{path}.{k}", f"focal length must be positive, got {kw[k]!r}")
    return Camera(**kw)


def _radiometry(d: Any) -> Radiometry:
    unit = _choice(_get(d, "unit", "radiometry"), UNITS, "radiometry.unit")
    scale = _number(_get(d, "scale", "radiometry"), "radiometry.scale")
    if scale == 0.0:
        raise PackageError("radiometry.scale", "must not be 0")
    return Radiometry(
        unit=unit, scale=scale, offset=_number(_get(d, "offset", "radiometry"), "radiometry.offset")
    )


def check_orthonormal(M: np.ndarray, field: str) -> None:
    """Refuse a `(3, 3)` matrix with |det − 1| > 1e-6 or ‖MᵀM − I‖ > 1e-6."""
    det = float(np.linalg.det(M))
    off = float(np.linalg.norm(M.T @ M - np.eye(3)))
    if abs(det - 1.0) > ORTHONORMAL_TOL or off > ORTHONORMAL_TOL:
        raise PackageError(field, f"not a rotation matrix (det = {det:.9g}, |MᵀM − I| = {off:.3g})")


def _mounting(d: Any, path: str = "mounting") -> Mounting:
    raw = _get(d, "camera_to_body", path)
    if not isinstance(raw, list) or len(raw) != 3:
        raise PackageError(f"{path}.camera_to_body", "expected a 3x3 array (3 rows)")
    M = np.stack([_vector(row, 3, f"{path}.camera_to_body[{i}]") for i, row in enumerate(raw)])
    check_orthonormal(M, f"{path}.camera_to_body")
    return Mounting(
        camera_to_body=M,
        boresight_deg=_vector(_get(d, "boresight_deg", path), 3, f"{path}.boresight_deg"),
        lever_arm_m=_vector(_get(d, "lever_arm_m", path), 3, f"{path}.lever_arm_m"),
    )


def _accuracy(d: Any, path: str = "accuracy") -> Accuracy:
    pos = _num_or_vector(_get(d, "position_m", path), f"{path}.position_m")
    att = _num_or_vector(_get(d, "attitude_deg", path), f"{path}.attitude_deg")
    for name, v in (("position_m", pos), ("attitude_deg", att)):
        if np.any(v <= 0):
            raise PackageError(f"{path}.{name}", "standard deviations must be positive")
    return Accuracy(position_m=pos, attitude_deg=att)


def _frames(raw: Any, root: Path | None, path: str = "frames") -> tuple[FrameRecord, ...]:
    if not isinstance(raw, list) or not raw:
        raise PackageError(path, "expected a non-empty array")
    out = []
    for i, f in enumerate(raw):
        p = f"{path}[{i}]"
        if not isinstance(f, Mapping):
            raise PackageError(p, "expected a JSON object")
        file = safe_relative(_get(f, "file", p), f"{p}.file")
        if root is not None:
            _existing_file(root, file, f"{p}.file")
        out.append(
            FrameRecord(
                index=i,
                file=file,
                time=_number(_get(f, "time", p), f"{p}.time"),
                position=_vector(_get(f, "position", p), 3, f"{p}.position"),
                attitude_deg=_vector(_get(f, "attitude_deg", p), 3, f"{p}.attitude_deg"),
            )
        )
        if i > 0 and not out[i].time > out[i - 1].time:
            raise PackageError(f"{p}.time", f"times must increase: {out[i].time!r} after {out[i - 1].time!r}")
    return tuple(out)


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
