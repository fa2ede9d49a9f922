"""The orient stage's RGB step (Hoegner & Stilla's method 3, `RunOptions.rgb`): the TIR block
registered onto the dense cloud of the package's RGB camera before the sequence orientation.

In: the ingested package (`job.Ingested`: the TIR frames in recording order, the manifest with
its optional `rgb_camera`, the package folder, the model's `srsName`) and the TIR poses to start
from (the calibrated priors, world = model CRS). Out: the poses the sequence orientation starts
from (the registered ones when the ICP was accepted, else the given ones) and the figures for
`report.json` (`sequence_orientation.rgb`).

The registration adjusts the TIR frames as one block from their own images and the priors
(`multiview`: consistent relative orientations for the stereo pairs), then moves the block by one
rigid transform (`rgb_method.orient_with_rgb`: SGBM dense clouds of both blocks, robust
point-to-plane ICP). It corrects the GNSS/INS offset common to the block, not the boresight or
the delay (the calibrate stage's); the block removes part of the per-frame noise, the sequence
orientation the rest: it runs between the two. On the bench drive (`bench/orientation_rgb.py`)
it takes the TIR positions from 2.5 m to 0.13 m off (0.19 m without the block); its CPU cost
(about 2-3 minutes per 48 frames) is why it is an option.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

from db.sequence_rgb import RgbFrames
from workers.pipeline.geometry.citymodel import ModelHeader
from workers.pipeline.geometry.manifest import FrameSource, SequenceManifest
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.reconstruction.rgb_method import orient_with_rgb, rgb_prior_poses


class _Ingested(Protocol):
    """What the step reads of `job.Ingested`."""

    package_dir: Any
    header: ModelHeader
    manifest: SequenceManifest
    frames: FrameSource

    @property
    def frame_indices(self) -> list[int]: ...


def rgb_registered(ingested: _Ingested, poses: Sequence[Pose]) -> tuple[list[Pose], dict[str, Any]]:
    """The TIR `poses` (one per frame, manifest order, world = model CRS) registered onto the RGB
    block of `ingested`'s package; `(poses, figures)`. Without an `rgb_camera` or when the ICP is
    not accepted the poses come back unchanged (`figures["accepted"]` False, with the reason)."""
    m = ingested.manifest
    if m.rgb is None:
        return list(poses), {"accepted": False, "reason": "the sequence has no rgb_camera"}
    frames = ingested.frame_indices
    reg = orient_with_rgb(
        lambda i: ingested.frames.load(frames[i]),
        m.camera,
        list(poses),
        RgbFrames(str(ingested.package_dir.resolve()), m.rgb).load,
        m.rgb.camera,
        rgb_prior_poses(m, ingested.header.srs_name),
    )
    return list(reg.poses), reg.figures()
