"""Sequence package domain objects (`citytherm-sequence/1`, see `docs/sequence-format.md`).

In: nothing (plain data, built by the reader in `db/sequence_package.py` or by `synth`).
Out: frozen dataclasses. Units: metres, seconds, degrees. Positions are in the manifest's `crs`
(not yet transformed; `georef` turns them into world poses in the model CRS).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

from workers.pipeline.geometry.camera import Camera

FORMAT = "citytherm-sequence/1"
Platform = Literal["drive", "flight", "terrestrial"]
HeadingReference = Literal["grid", "true"]


@dataclass(frozen=True)
class Radiometry:
    """Physical value = `DN · scale + offset`, in `unit` (`"K"`, `"degC"` or `"counts"`)."""

    unit: str = "K"
    scale: float = 0.01
    offset: float = 0.0

    def physical(self, dn: np.ndarray) -> np.ndarray:
        """Digital numbers `(H, W)` -> float32 physical values in `unit`."""
        return (np.asarray(dn, dtype=np.float32) * np.float32(self.scale) + np.float32(self.offset)).astype(
            np.float32
        )

    def dn(self, value: np.ndarray) -> np.ndarray:
        """Physical values -> uint16 DN (rounded, clipped to 1..65535; NaN -> 0 = not observed)."""
        v = np.asarray(value, dtype=np.float64)
        d = np.rint((v - self.offset) / self.scale)
        out = np.clip(np.nan_to_num(d, nan=0.0), 1, 65535).astype(np.uint16)
        out[~np.isfinite(v)] = 0
        return out


@dataclass(frozen=True, eq=False)
class Mounting:
    """Camera mounting on the platform.

    Attributes:
        camera_to_body: `(3, 3)` nominal rotation `M` (camera axes -> body axes).
        boresight_deg: `(3,)` misalignment `[bx, by, bz]` about body x, y, z, degrees;
            `R_bc = Rz(bz) · Ry(by) · Rx(bx) · M`.
        lever_arm_m: `(3,)` camera centre from the IMU reference point in body axes, metres.
    """

    camera_to_body: np.ndarray
    boresight_deg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True, eq=False)
class Accuracy:
    """A-priori standard deviations of the GNSS/INS solution: `position_m` `(3,)` east, north,
    up in metres; `attitude_deg` `(3,)` roll, pitch, heading in degrees."""

    position_m: np.ndarray
    attitude_deg: np.ndarray


@dataclass(frozen=True, eq=False)
class FrameRecord:
    """One frame of the manifest: `position` `(3,)` of the IMU reference point in the manifest's
    `crs`, `attitude_deg` `(3,)` = `[roll, pitch, heading]`, `time` in seconds."""

    index: int
    file: str
    time: float
    position: np.ndarray
    attitude_deg: np.ndarray


@dataclass(frozen=True, eq=False)
class ImuSamples:
    """High-rate GNSS/INS solution: `time` `(N,)`, `position` `(N, 3)`, `attitude_deg` `(N, 3)`,
    same clock, CRS and conventions as the frames."""

    time: np.ndarray
    position: np.ndarray
    attitude_deg: np.ndarray


@dataclass(frozen=True, eq=False)
class GroundControl:
    """Ground control points: `points` id -> (`xyz` `(3,)` in `crs`, `sigma_m` or None);
    `observations` as `(frame index, point id, uv (2,) pixels)`."""

    points: dict[str, tuple[np.ndarray, float | None]]
    observations: tuple[tuple[int, str, np.ndarray], ...]


@dataclass(frozen=True)
class Conditions:
    """Conditions of the survey (`conditions` of the manifest; every member optional).

    Attributes:
        air_temperature_c: outside air temperature during the recording, degrees Celsius (None:
            not given). Used to normalise the change between two surveys
            (`workers.pipeline.change`).
        recorded_at: when the recording started, ISO 8601 with a UTC offset
            (`2025-01-15T21:30:00+01:00`, `...Z`), as written (None: not given).
    """

    air_temperature_c: float | None = None
    recorded_at: str | None = None

    @property
    def air_temperature_k(self) -> float | None:
        """`air_temperature_c` in kelvin (None when not given).

        >>> Conditions(air_temperature_c=-3.5).air_temperature_k
        269.65
        """
        if self.air_temperature_c is None:
            return None
        return round(self.air_temperature_c + 273.15, 9)

    def to_dict(self) -> dict[str, float | str]:
        """The manifest's `conditions` object (members that are given only)."""
        out: dict[str, float | str] = {}
        if self.air_temperature_c is not None:
            out["air_temperature_c"] = float(self.air_temperature_c)
        if self.recorded_at is not None:
            out["recorded_at"] = self.recorded_at
        return out


@dataclass(frozen=True, eq=False)
class SecondCamera:
    """The optional second (visible-band, RGB) camera on the same mount (`rgb_camera` of the
    manifest, section `version` 1; see `docs/sequence-format.md`).

    Attributes:
        camera: interior orientation (OPENCV model, pixel centres at integers).
        mounting: its mounting on the INS body, the same convention as the TIR camera's.
        frames: its frames; `position` / `attitude_deg` are the INS-body solution that, with
            `mounting`, gives this camera's pose (as for TIR frames), `time` on the INS clock.
        channels: 3 (8-bit RGB) or 1 (8-bit grey).
        pose_source: `"ins"` (the GNSS/INS solution) or `"photogrammetric"` (an adjusted block,
            e.g. with ground control: more accurate than the INS).
        accuracy: a-priori standard deviations of these poses (None: those of `accuracy`).
    """

    camera: Camera
    mounting: Mounting
    frames: tuple[FrameRecord, ...]
    channels: int = 3
    pose_source: str = "ins"
    accuracy: Accuracy | None = None


@dataclass(frozen=True, eq=False)
class SequenceManifest:
    """The parsed `sequence.json` (everything but the pixels)."""

    platform: str
    crs: str
    camera: Camera
    radiometry: Radiometry
    mounting: Mounting
    frames: tuple[FrameRecord, ...]
    heading_reference: str = "grid"
    vertical_offset_m: float = 0.0
    accuracy: Accuracy | None = None
    imu: ImuSamples | None = None
    gcps: GroundControl | None = None
    format: str = FORMAT
    conditions: Conditions | None = None  # survey conditions (air temperature), when given
    rgb: SecondCamera | None = None  # the optional RGB camera (`rgb_camera`), when given


class FrameSource(Protocol):
    """Something that yields a frame's physical values: `load(index) -> (H, W) float32`.

    Implementations must be picklable (they travel with building units to worker processes).
    """

    def load(self, index: int) -> np.ndarray:
        """Frame `index` as float32 physical values (radiometry applied), shape `(H, W)`."""
        ...


@dataclass(frozen=True, eq=False)
class MemoryFrames:
    """An in-memory `FrameSource` (tests, benches, demos): frames already decoded.

    Attributes:
        frames: frame index -> `(H, W)` physical values (a mapping, or a sequence indexed 0..N-1).
    """

    frames: Mapping[int, np.ndarray] | Sequence[np.ndarray]

    def load(self, index: int) -> np.ndarray:
        """Frame `index` as float32 `(H, W)` (no copy when it is float32 already)."""
        return np.asarray(self.frames[index], dtype=np.float32)
