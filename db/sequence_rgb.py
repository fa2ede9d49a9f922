"""The optional second camera of a sequence package: `rgb_camera` (section version 1).

In: the decoded `rgb_camera` object of `sequence.json` and the package root; RGB frame files.
Out: `workers.pipeline.geometry.manifest.SecondCamera` (positions still in the manifest's `crs`);
`RgbFrames`, a picklable loader `load(i) -> (H, W, 3) uint8` RGB (or `(H, W)` grey); the inverse
`rgb_camera_to_dict`; `write_rgb_frames`.

The section (see `docs/sequence-format.md`, *A second camera*):
`{"version": 1, "camera": {...}, "channels": 3, "mounting": {...}, "pose_source": "ins" |
"photogrammetric", "accuracy": {...}, "frames": [{"file", "time", "position", "attitude_deg"}]}`:
the same field conventions as the TIR camera's `camera`, `mounting`, `accuracy` and `frames`.
Every refusal raises `PackageError` naming the field (`rgb_camera.frames[2].time`) or file.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from db.sequence_fields import (
    PackageError,
    _accuracy,
    _camera,
    _choice,
    _frames,
    _get,
    _mounting,
    _number,
    safe_relative,
)
from workers.pipeline.geometry.manifest import SecondCamera

SECTION = "rgb_camera"
VERSIONS = (1,)
POSE_SOURCES = ("ins", "photogrammetric")
CHANNELS = (1, 3)


def parse_rgb_camera(d: Any, root: Path | None = None) -> SecondCamera:
    """Decoded `rgb_camera` -> `SecondCamera`. With `root`, its frame files must exist."""
    if not isinstance(d, Mapping):
        raise PackageError(SECTION, "expected a JSON object")
    version = _number(_get(d, "version", SECTION), f"{SECTION}.version")
    if version not in VERSIONS:
        known = list(VERSIONS)
        raise PackageError(f"{SECTION}.version", f"unknown section version {d['version']!r} (known: {known})")
    channels = _number(d.get("channels", 3), f"{SECTION}.channels")
    if channels not in CHANNELS:
        raise PackageError(f"{SECTION}.channels", f"expected 1 or 3, got {d.get('channels')!r}")
    source = _choice(d.get("pose_source", "ins"), POSE_SOURCES, f"{SECTION}.pose_source")
    acc = d.get("accuracy")
    return SecondCamera(
        camera=_camera(_get(d, "camera", SECTION), f"{SECTION}.camera"),
        mounting=_mounting(_get(d, "mounting", SECTION), f"{SECTION}.mounting"),
        frames=_frames(_get(d, "frames", SECTION), root, f"{SECTION}.frames"),
        channels=int(channels),
        pose_source=source,
        accuracy=None if acc is None else _accuracy(acc, f"{SECTION}.accuracy"),
    )


def rgb_camera_to_dict(rgb: SecondCamera) -> dict[str, Any]:
    """`SecondCamera` -> the JSON object of `rgb_camera` (plain lists and floats)."""

    def vec(a: np.ndarray) -> list[float]:
        return np.asarray(a, dtype=float).reshape(-1).tolist()

    m = rgb.mounting
    d: dict[str, Any] = {
        "version": VERSIONS[-1],
        "camera": rgb.camera.to_dict(),
        "channels": int(rgb.channels),
        "mounting": {
            "camera_to_body": np.asarray(m.camera_to_body, dtype=float).reshape(3, 3).tolist(),
            "boresight_deg": vec(m.boresight_deg),
            "lever_arm_m": vec(m.lever_arm_m),
        },
        "pose_source": rgb.pose_source,
    }
    if rgb.accuracy is not None:
        a = rgb.accuracy
        d["accuracy"] = {"position_m": vec(a.position_m), "attitude_deg": vec(a.attitude_deg)}
    d["frames"] = [
        {"file": f.file, "time": float(f.time), "position": vec(f.position),
         "attitude_deg": vec(f.attitude_deg)}
        for f in rgb.frames
    ]
    return d


def read_rgb_raw(path: Path, name: str, rgb: SecondCamera) -> np.ndarray:
    """One RGB frame file -> `(H, W, 3)` uint8 in R, G, B order (`(H, W)` for `channels` 1);
    refuses unreadable files, other sample types, channel counts and sizes, naming `name`."""
    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise PackageError(name, "unreadable frame (missing or not an image)")
    if arr.dtype != np.uint8:
        raise PackageError(name, f"expected an 8-bit image, got {arr.dtype}")
    got = 1 if arr.ndim == 2 else arr.shape[2]
    if got != rgb.channels:
        raise PackageError(name, f"expected {rgb.channels} channel(s), got {got}")
    cam = rgb.camera
    if arr.shape[:2] != (cam.height, cam.width):
        size = f"{arr.shape[1]}x{arr.shape[0]}"
        raise PackageError(name, f"frame size {size} differs from the rgb camera's {cam.width}x{cam.height}")
    return arr if arr.ndim == 2 else np.ascontiguousarray(arr[:, :, ::-1])


def check_rgb_frames(rgb: SecondCamera, root: Path) -> None:
    """Decode the header of every RGB frame: 8 bits, `channels`, the camera's size."""
    from PIL import Image

    cam = rgb.camera
    for f in rgb.frames:
        try:
            with Image.open(root / f.file) as im:
                bands, size, mode = len(im.getbands()), (im.width, im.height), im.mode
        except Exception as exc:  # any decoder error: unreadable
            raise PackageError(f.file, f"unreadable frame: {exc}") from exc
        if mode not in ("L", "RGB"):
            raise PackageError(f.file, f"expected an 8-bit grey or RGB image, got mode {mode}")
        if bands != rgb.channels:
            raise PackageError(f.file, f"expected {rgb.channels} channel(s), got {bands}")
        if size != (cam.width, cam.height):
            got, want = f"{size[0]}x{size[1]}", f"{cam.width}x{cam.height}"
            raise PackageError(f.file, f"frame size {got} differs from the rgb camera's {want}")


@dataclass(frozen=True, eq=False)
class RgbFrames:
    """Picklable loader of a package's RGB frames: `load(i) -> (H, W, 3)` uint8 RGB (or
    `(H, W)` grey for `channels` 1), in `rgb.frames` order; `len()` frames."""

    root: str
    rgb: SecondCamera

    def __len__(self) -> int:
        return len(self.rgb.frames)

    def load(self, index: int) -> np.ndarray:
        """Frame `index` as stored (size and channels checked)."""
        name = self.rgb.frames[index].file
        return read_rgb_raw(Path(self.root) / name, name, self.rgb)


def write_rgb_frames(out: Path, rgb: SecondCamera, frames: Iterable[np.ndarray]) -> None:
    """Write one 8-bit PNG per `rgb.frames` entry: `(H, W, 3)` uint8 RGB or `(H, W)` grey."""
    n = 0
    for rec, arr in zip(rgb.frames, frames, strict=False):
        name = safe_relative(rec.file, f"{SECTION}.frames[{rec.index}].file")
        a = np.asarray(arr)
        want = (rgb.camera.height, rgb.camera.width) + ((3,) if rgb.channels == 3 else ())
        if a.dtype != np.uint8 or a.shape != want:
            raise PackageError(name, f"expected uint8 {want}, got {a.dtype} {a.shape}")
        target = out / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(target), a[:, :, ::-1] if a.ndim == 3 else a):
            raise PackageError(name, "could not write the frame")
        n += 1
    if n != len(rgb.frames):
        raise PackageError(SECTION, f"{n} images given for {len(rgb.frames)} rgb frames")
