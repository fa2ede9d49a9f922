"""Sequence packages (`citytherm-sequence/1`): open a directory or archive, read frames, write one.

In: a package path: a folder holding `sequence.json`, or a `.zip` / `.tar` / `.tar.gz` of one
(the manifest at the archive root or inside its single top-level folder).
Out: `SequencePackage` with the parsed `manifest` (`SequenceManifest`, positions still in the
manifest's `crs`), the package `root` folder, and `frames` (`PackageFrames`, a picklable
`FrameSource`: `load(i) -> (H, W) float32` physical values, radiometry applied).

Frame values: 16-bit PNG / TIFF are DNs, turned into `DN · scale + offset`; DN 0 is "not observed"
and becomes NaN (the inverse of `Radiometry.dn`). Float TIFFs get the radiometry applied too.
8-bit PNGs are uncalibrated display values and are returned as they are (0..255).

Archives are extracted safely (`db.sequence_archive`) into a temporary folder owned by the
package: use it as a context manager or call `close()` (frames cannot be loaded afterwards).
Every refusal raises `PackageError` (a `ValueError`) with `.field` naming the field or file.
"""

from __future__ import annotations

import functools
import json
import shutil
import tempfile
import weakref
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
import tifffile
from PIL import Image

from db.sequence_archive import archive_kind, extract_archive
from db.sequence_manifest import (
    PackageError,
    gcps_to_dict,
    manifest_to_dict,
    parse_manifest,
    safe_relative,
    write_imu_csv,
)
from db.sequence_rgb import RgbFrames, check_rgb_frames, write_rgb_frames
from workers.pipeline.geometry.manifest import Radiometry, SequenceManifest

__all__ = [
    "DEFAULT_MAX_BYTES",
    "DEFAULT_MAX_MEMBERS",
    "MANIFEST",
    "PackageError",
    "PackageFrames",
    "SequencePackage",
    "find_root",
    "manifest_to_dict",
    "open_package",
    "read_frame_raw",
    "write_package",
]

MANIFEST = "sequence.json"
DEFAULT_MAX_BYTES = 20 * 1024**3  # 20 GiB expanded, as `Settings.max_package_bytes`
DEFAULT_MAX_MEMBERS = 200_000  # as `Settings.max_package_members`
TIFF_SUFFIXES = (".tif", ".tiff")


# -- frames --------------------------------------------------------------------------------------
def _frame_header(path: Path, name: str) -> tuple[int, int, int]:
    """(height, width, channels) of a frame from its header, without decoding the pixels."""
    try:
        if path.suffix.lower() in TIFF_SUFFIXES:
            with tifffile.TiffFile(path) as tf:
                page = tf.pages[0]
                return int(page.imagelength), int(page.imagewidth), int(page.samplesperpixel)
        with Image.open(path) as im:
            return im.height, im.width, len(im.getbands())
    except Exception as exc:  # any decoder error means: unreadable frame
        raise PackageError(name, f"unreadable frame: {exc}") from exc


def read_frame_raw(path: Path, name: str | None = None) -> np.ndarray:
    """The stored values of one frame file: `(H, W)` uint8, uint16, float32 or float64.

    Refuses multi-channel and other sample types with `PackageError` naming `name`.
    """
    name = name or path.name
    try:
        if path.suffix.lower() in TIFF_SUFFIXES:
            arr = tifffile.imread(path)
        else:
            arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except Exception as exc:
        raise PackageError(name, f"unreadable frame: {exc}") from exc
    if arr is None:
        raise PackageError(name, "unreadable frame (missing or not an image)")
    arr = np.asarray(arr)
    if arr.ndim != 2:
        raise PackageError(name, f"expected a single-channel image, got shape {arr.shape}")
    if arr.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise PackageError(name, f"unsupported sample type {arr.dtype} (8/16-bit or float expected)")
    return arr


def physical_from_raw(arr: np.ndarray, radiometry: Radiometry) -> np.ndarray:
    """Stored frame values -> float32 physical values `(H, W)`, a fresh array (see module doc).
    16-bit DNs convert by one gather from `dn_table` (bit for bit `Radiometry.physical`)."""
    if arr.dtype == np.uint8:
        return arr.astype(np.float32)
    if arr.dtype == np.uint16:
        return np.take(dn_table(radiometry), arr)
    return radiometry.physical(arr)


@functools.lru_cache(maxsize=16)
def dn_table(radiometry: Radiometry) -> np.ndarray:
    """`(65536,)` float32 physical value of every 16-bit DN (`Radiometry.physical`, elementwise, so
    a gather from it equals converting the frame), NaN at DN 0 (not observed); read-only, one per
    radiometry and process. A gather costs half of the conversion and a third of it against a
    float32 copy held in the frame cache (640 x 512: 0.8 ms against 1.7 ms)."""
    table = radiometry.physical(np.arange(65536, dtype=np.uint16))
    table[0] = np.nan
    table.flags.writeable = False
    return table


#: bytes of decoded frames kept per process (`PackageFrames.raw`)
FRAME_CACHE_BYTES = 256 * 1024**2
_FRAMES: OrderedDict[tuple[object, ...], np.ndarray] = OrderedDict()
_CACHED_BYTES = [0]  # bytes held in `_FRAMES`, kept as frames come and go (no sum per insert)


def _remember(key: tuple[object, ...], arr: np.ndarray) -> None:
    """Keep a decoded frame, dropping the least recently used beyond `FRAME_CACHE_BYTES`; O(1)
    per frame (a running byte total: at small frame sizes the cache holds thousands)."""
    previous = _FRAMES.pop(key, None)
    if previous is not None:
        _CACHED_BYTES[0] -= previous.nbytes
    _FRAMES[key] = arr
    _CACHED_BYTES[0] += arr.nbytes
    while _CACHED_BYTES[0] > FRAME_CACHE_BYTES and len(_FRAMES) > 1:
        _, old = _FRAMES.popitem(last=False)
        _CACHED_BYTES[0] -= old.nbytes


@dataclass(frozen=True)
class PackageFrames:
    """Picklable `FrameSource` over a package folder: `load(i) -> (H, W) float32` physical values.

    Attributes:
        root: package folder (absolute path as a string).
        files: frame file names relative to `root`, in manifest order.
        width, height: the camera's image size in pixels (checked on every load).
        radiometry: DN -> physical value mapping.
    """

    root: str
    files: tuple[str, ...]
    width: int
    height: int
    radiometry: Radiometry

    def __len__(self) -> int:
        return len(self.files)

    def raw(self, index: int) -> np.ndarray:
        """Frame `index` as stored (uint8 / uint16 / float), shape `(H, W)`, size checked; read-only.

        Decoded frames are kept per process (`FRAME_CACHE_BYTES`, least recently used first out,
        keyed by file, size and modification time): the building units of a flight read the same
        frames dozens of times, and decoding is most of a frame's cost."""
        name = self.files[index]
        path = Path(self.root) / name
        try:
            st = path.stat()
            key: tuple[str, int, int] | None = (str(path), st.st_size, st.st_mtime_ns)
        except OSError:
            key = None  # read_frame_raw names the missing file
        if key is not None and (hit := _FRAMES.get(key)) is not None:
            _FRAMES.move_to_end(key)
            return hit
        arr = read_frame_raw(path, name)
        if arr.shape != (self.height, self.width):
            raise PackageError(
                name,
                f"frame size {arr.shape[1]}x{arr.shape[0]} differs from the camera's "
                f"{self.width}x{self.height}",
            )
        arr.flags.writeable = False
        if key is not None:
            _remember(key, arr)
        return arr

    def load(self, index: int) -> np.ndarray:
        """Frame `index` as float32 physical values (radiometry applied), shape `(H, W)`; a fresh
        array, converted from the decoded frame of the per-process cache (`raw`). Only the decoded
        frames are kept (16-bit: 0.6 MB at 640 x 512, a third of the decoded and converted pair
        the cache held before): the 256 MiB hold a 300-frame drive whole, so each process decodes
        a frame once, and converting (`physical_from_raw`) costs less than a fifth of decoding."""
        return physical_from_raw(self.raw(index), self.radiometry)


# -- package -------------------------------------------------------------------------------------
class SequencePackage:
    """An opened sequence package: `manifest`, `root` folder and lazily loaded `frames`.

    Owns the temporary folder of an extracted archive; `close()` (or leaving the `with` block)
    removes it.
    """

    def __init__(self, manifest: SequenceManifest, root: Path, tmp: Path | None = None) -> None:
        self.manifest = manifest
        self.root = root
        self.frames = PackageFrames(
            root=str(root.resolve()),
            files=tuple(f.file for f in manifest.frames),
            width=manifest.camera.width,
            height=manifest.camera.height,
            radiometry=manifest.radiometry,
        )
        #: the second (RGB) camera's frames (`load(i) -> (H, W, 3)` uint8), None without one
        self.rgb_frames = None if manifest.rgb is None else RgbFrames(str(root.resolve()), manifest.rgb)
        self._tmp = tmp
        self._finalizer = (
            weakref.finalize(self, shutil.rmtree, str(tmp), ignore_errors=True) if tmp is not None else None
        )

    def close(self) -> None:
        """Remove the temporary extraction folder (no-op for a plain directory)."""
        if self._finalizer is not None:
            self._finalizer()

    def __enter__(self) -> SequencePackage:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"SequencePackage(root={str(self.root)!r}, frames={len(self.manifest.frames)})"


def find_root(folder: Path) -> Path:
    """The folder holding `sequence.json`: `folder`, or its single top-level folder (as archives
    are often packed). Raises `PackageError` naming the manifest when there is none."""
    if (folder / MANIFEST).is_file():
        return folder
    children = [c for c in folder.iterdir() if not c.name.startswith(".") and c.name != "__MACOSX"]
    if len(children) == 1 and children[0].is_dir() and (children[0] / MANIFEST).is_file():
        return children[0]
    raise PackageError(MANIFEST, "missing at the package root")


def _check_frames(manifest: SequenceManifest, root: Path) -> None:
    cam = manifest.camera
    for f in manifest.frames:
        h, w, c = _frame_header(root / f.file, f.file)
        if c != 1:
            raise PackageError(f.file, f"expected a single-channel image, got {c} channels")
        if (h, w) != (cam.height, cam.width):
            raise PackageError(
                f.file, f"frame size {w}x{h} differs from the camera's {cam.width}x{cam.height}"
            )


def read_manifest(root: Path, *, check_frames: bool = True) -> SequenceManifest:
    """Parse `root/sequence.json` (and its imu/gcps files); optionally check every frame's
    header (exists, readable, single channel, camera size)."""
    try:
        d = json.loads((root / MANIFEST).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise PackageError(MANIFEST, "missing at the package root") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PackageError(MANIFEST, f"unreadable JSON: {exc}") from exc
    manifest = parse_manifest(d, root)
    if check_frames:
        _check_frames(manifest, root)
        if manifest.rgb is not None:
            check_rgb_frames(manifest.rgb, root)
    return manifest


def open_package(
    path: str | Path,
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
    max_members: int = DEFAULT_MAX_MEMBERS,
    check_frames: bool = True,
) -> SequencePackage:
    """Open a package folder, `sequence.json` file, or `.zip` / `.tar` / `.tar.gz` archive.

    Archives are extracted (within `max_bytes` expanded bytes and `max_members` members) into a
    temporary folder that the returned package owns. Raises `PackageError` on any refusal.
    """
    p = Path(path)
    if not p.exists():
        raise PackageError(str(path), "package not found")
    if p.is_dir():
        return SequencePackage(read_manifest(find_root(p), check_frames=check_frames), find_root(p))
    if p.name == MANIFEST:
        return SequencePackage(read_manifest(p.parent, check_frames=check_frames), p.parent)
    if archive_kind(p) is None:
        raise PackageError(p.name, "not a package folder, sequence.json, zip or tar archive")
    tmp = Path(tempfile.mkdtemp(prefix="citytherm-seq-"))
    try:
        extract_archive(p, tmp, max_bytes=max_bytes, max_members=max_members)
        root = find_root(tmp)
        return SequencePackage(read_manifest(root, check_frames=check_frames), root, tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


# -- writing -------------------------------------------------------------------------------------
def _frame_for_file(arr: np.ndarray, file: str, radiometry: Radiometry) -> np.ndarray:
    a = np.asarray(arr)
    if file.lower().endswith(TIFF_SUFFIXES):
        if a.dtype not in (np.uint16, np.float32):
            a = a.astype(np.float32)
        return a
    if a.dtype in (np.uint16, np.uint8):
        return a
    if np.issubdtype(a.dtype, np.floating):
        return radiometry.dn(a)  # physical values -> DN (NaN -> 0)
    raise PackageError(file, f"cannot write sample type {a.dtype} as PNG (uint8, uint16 or float)")


def write_package(
    out_dir: str | Path,
    manifest: SequenceManifest,
    frames: Iterable[np.ndarray],
    rgb_frames: Iterable[np.ndarray] | None = None,
) -> Path:
    """Write a package folder: `sequence.json`, one image per manifest frame, `imu.csv` and
    `gcps.json` when the manifest has them, and the RGB frames (`rgb_frames`: `(H, W, 3)` uint8
    RGB, required when `manifest.rgb` is set). Returns the folder.

    `frames` yields `(H, W)` arrays in manifest order: uint16 DNs or uint8 for `.png` files
    (float arrays are taken as physical values and converted with `radiometry.dn`), uint16 or
    float32 for `.tif` files.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cam = manifest.camera
    n = 0
    it = iter(frames)
    for rec, arr in zip(manifest.frames, it, strict=False):
        name = safe_relative(rec.file, f"frames[{rec.index}].file")
        a = _frame_for_file(arr, name, manifest.radiometry)
        if a.shape != (cam.height, cam.width):
            raise PackageError(
                name, f"frame shape {a.shape} differs from the camera's {(cam.height, cam.width)}"
            )
        target = out / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if name.lower().endswith(TIFF_SUFFIXES):
            tifffile.imwrite(target, a)
        elif not cv2.imwrite(str(target), a):
            raise PackageError(name, "could not write the frame")
        n += 1
    if n == len(manifest.frames) and next(it, None) is not None:
        n += 1
    if n != len(manifest.frames):
        raise PackageError("frames", f"{n} images given for {len(manifest.frames)} manifest frames")
    if manifest.rgb is not None:
        if rgb_frames is None:
            raise PackageError("rgb_camera", "the manifest has an rgb camera but no rgb frames were given")
        write_rgb_frames(out, manifest.rgb, rgb_frames)
    d: dict[str, Any] = manifest_to_dict(manifest)
    if manifest.imu is not None:
        write_imu_csv(out / d["imu"], manifest.imu)
    if manifest.gcps is not None:
        (out / d["gcps"]).write_text(json.dumps(gcps_to_dict(manifest.gcps), indent=1), encoding="utf-8")
    (out / MANIFEST).write_text(json.dumps(d, indent=1), encoding="utf-8")
    return out
