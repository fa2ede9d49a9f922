"""The two images of every thermal texture in the glTF content, and the value scales they use.

In: a 16-bit texture tile (DN `(H, W)` uint16, 0 = not observed) and its radiometry
(`value = DN · scale + offset` in K, degC or counts). Out: PNG bytes of

- the *display* image: 8-bit RGB, the value colour-mapped with OpenCV's `inferno` over a fixed
  range `[lo, hi]` (`DisplayScale`): colour index `i = clip(round_down((v - lo) / (hi - lo) · 254
  + 1), 1, 255)`, i.e. index `i` shows `lo + (i - 1) / 254 · (hi - lo)`; not observed: black
  (the rule of the results folder's `-display` copies);
- the *value* image: 8-bit RGB with the DN's low byte in red and its high byte in green (blue 0):
  an `EXT_structural_metadata` property texture with `channels [0, 1]` (little-endian UINT16),
  `normalized: true`, so the temperature is `offset + scale · DN / 65535` with `ValueScale`'s
  kelvin offset and scale, and DN 0 the `noData` value.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.geometry.manifest import Radiometry

__all__ = ["DisplayScale", "ValueScale", "display_png", "png_bytes", "value_png"]

ZERO_C_K = 273.15


@dataclass(frozen=True)
class ValueScale:
    """DN -> the exported value: `value = dn · scale + offset` in `unit` ("K" for temperatures,
    "counts" for uncalibrated input). `metadata_scale` is the `EXT_structural_metadata` scale of a
    normalized UINT16 (`scale · 65535`)."""

    unit: str
    scale: float
    offset: float

    @classmethod
    def of(cls, radiometry: Radiometry) -> ValueScale:
        """Kelvin for K and degC radiometry (degC shifted by 273.15), counts as they are."""
        if radiometry.unit == "degC":
            return cls("K", float(radiometry.scale), float(radiometry.offset) + ZERO_C_K)
        if radiometry.unit == "K":
            return cls("K", float(radiometry.scale), float(radiometry.offset))
        return cls("counts", float(radiometry.scale), float(radiometry.offset))

    @property
    def metadata_scale(self) -> float:
        """Scale of the normalized UINT16 property (`value = offset + metadata_scale · dn / 65535`)."""
        return self.scale * 65535.0

    def value(self, dn: np.ndarray) -> np.ndarray:
        """DN -> float64 values (NaN where DN is 0)."""
        d = np.asarray(dn)
        out = d.astype(np.float64) * self.scale + self.offset
        out[d == 0] = np.nan
        return out

    def to_unit(self, value: float, unit: str | None) -> float:
        """A statistic given in a radiometry `unit` ("K", "degC", "counts") -> this scale's unit."""
        if unit == "degC" and self.unit == "K":
            return value + ZERO_C_K
        return value


@dataclass(frozen=True)
class DisplayScale:
    """The fixed colour scale of the display images: `colormap` from `lo` to `hi` (in the
    `ValueScale` unit, kelvin for temperatures)."""

    lo: float
    hi: float
    colormap: str = "inferno"

    def index(self, value: np.ndarray) -> np.ndarray:
        """Values -> colour index 1..255 (uint8); NaN -> 0."""
        v = np.asarray(value, dtype=np.float64)
        i = np.clip((v - self.lo) / max(self.hi - self.lo, 1e-6) * 254.0 + 1.0, 1, 255)
        return np.where(np.isfinite(v), i, 0).astype(np.uint8)

    def rgb(self, value: np.ndarray) -> np.ndarray:
        """Values `(H, W)` -> `(H, W, 3)` uint8 RGB of the colour map, NaN black."""
        idx = self.index(value)
        bgr = cv2.applyColorMap(idx, cv2.COLORMAP_INFERNO)
        bgr[idx == 0] = 0
        return np.ascontiguousarray(bgr[..., ::-1])

    def legend(self) -> list[list[int]]:
        """The 255 colours `[r, g, b]` of indexes 1..255 (index `i` shows `lo + (i-1)/254·(hi-lo)`)."""
        return self.rgb(np.linspace(self.lo, self.hi, 255)[None, :])[0].tolist()


def png_bytes(rgb: np.ndarray) -> bytes:
    """`(H, W, 3)` uint8 RGB -> PNG bytes."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise ValueError("PNG encoder failed")
    return buf.tobytes()


def display_png(dn: np.ndarray, values: ValueScale, scale: DisplayScale) -> bytes:
    """The display image of a 16-bit tile (see the module docstring)."""
    return png_bytes(scale.rgb(values.value(dn)))


def value_png(dn: np.ndarray) -> bytes:
    """The value image of a 16-bit tile: red = low byte, green = high byte of the DN."""
    d = np.asarray(dn, dtype=np.uint16)
    rgb = np.zeros((*d.shape, 3), dtype=np.uint8)
    rgb[..., 0] = d & 0xFF
    rgb[..., 1] = d >> 8
    return png_bytes(rgb)
