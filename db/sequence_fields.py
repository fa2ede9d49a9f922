"""The field readers of `sequence.json` (`db.sequence_manifest`, `db.sequence_rgb`): numbers,
vectors, choices, safe relative paths, camera, radiometry, mounting, accuracy and frame records,
each refusing with a `PackageError` whose `.field` names the offending field (`frames[3].position[1]`)
or file.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import Accuracy, FrameRecord, Mounting, Radiometry

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
