"""Frames whose observations contradict the other frames': distrusted as a whole, after fusion.

In: the fused `SurfaceTexture`s of one unit's surfaces (every texel's kept observations with
their frames, `fused`), the observation noise of `FusedOptions` (radiometry unit, kelvin).
Out: the frames dropped (their observations removed from every texture and the touched texels
fused again), `reject_inconsistent_frames`.

Why per frame: a pose error belongs to the frame, not to a texel. A frame whose pose is off by a
few pixels (a pose the refinement confirmed from one or two edge matches) shifts its whole view
of the building: on a roof seen from the street at a grazing angle it lays the sky or the wall
below onto the roof's texels, and the clean-pixel test, made with the same wrong pose, finds
its footprints clean. Per texel, the median of the kept observations rejects such a view only
where at least three frames overlap; where it meets one other frame (the finer one decides) or
none, it stands. Pooled over every texel the frame shares with other frames, the contradiction
is plain: on the synthetic NRW drive with true poses no frame has more than 0.1 % of its shared
texels farther than `outlier_sigmas · noise` from the median of the texel's observations;
a frame whose sequence pose is 0.8° off (4 px on the building) has 45–54 %, in each of the three
buildings it sees, while the median frame of those buildings has none (`max_outlier_share`,
`relative`). The frame with the largest share goes first and the
shares are computed again without it (the frames it contradicted are cleared of its votes),
until no frame exceeds the share.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from workers.pipeline.texture.fused import SurfaceTexture, sorted_columns


@dataclass(frozen=True)
class ConsistencyOptions:
    """When a frame's observations are dropped from a unit's textures.

    Attributes:
        enabled: run the test (False: every frame's observations stay).
        max_outlier_share: a frame whose observations lie farther than `outlier_sigmas · noise`
            (`fused.FusedOptions`) from the median of the observations of the same texel on more
            than this share of the texels it shares with other frames is dropped.
        min_shared: a frame sharing fewer texels than this with other frames is never judged.
        relative: ... and only when its share is also more than this many times the median share
            of the unit's judged frames: a frame is dropped for contradicting frames that agree
            among themselves, not when every frame disagrees (a surface whose temperature
            changed between two passes of a long sequence).
    """

    enabled: bool = True
    max_outlier_share: float = 0.25
    min_shared: int = 20
    relative: float = 3.0


def frame_disagreement(textures: Sequence[SurfaceTexture], threshold: float) -> dict[int, tuple[int, int]]:
    """Per frame `(shared, outliers)` over `textures`: the texels where the frame holds an
    observation and at least one other frame does too, and of those the ones where the frame's
    value lies farther than `threshold` from the median of all the texel's observations (with
    two, their mean: both count when they differ by more than twice `threshold`)."""
    shared: dict[int, int] = {}
    outl: dict[int, int] = {}
    for tex in textures:
        K = tex.obs_frame.shape[0]
        f = tex.obs_frame.reshape(K, -1)
        v = tex.obs_value.reshape(K, -1)
        ok = (f >= 0) & np.isfinite(v)
        n = ok.sum(axis=0)
        cols = np.flatnonzero(n >= 2)
        if len(cols) == 0:
            continue
        f, v, ok, n = f[:, cols], v[:, cols], ok[:, cols], n[cols]
        srt = sorted_columns(np.where(ok, v, np.inf).astype(np.float32))
        idx = np.arange(len(cols))
        med = 0.5 * (srt[(n - 1) // 2, idx] + srt[n // 2, idx])
        bad = ok & (np.abs(v - med[None, :]) > threshold)
        for frames, counts in ((f[ok], shared), (f[bad], outl)):
            u, c = np.unique(frames, return_counts=True)
            for frame, cnt in zip(u.tolist(), c.tolist(), strict=True):
                counts[frame] = counts.get(frame, 0) + cnt
    return {fr: (n_sh, outl.get(fr, 0)) for fr, n_sh in shared.items()}


def reject_inconsistent_frames(
    textures: Sequence[SurfaceTexture], options: ConsistencyOptions = ConsistencyOptions()
) -> list[int]:
    """Drop, one after the other, the frames whose observations contradict the other frames'
    (module docstring) from `textures` (in place: their observations removed, the touched texels
    fused again). Returns the dropped frames in the order they went."""
    if not options.enabled or not textures:
        return []
    fo = textures[0].options
    threshold = float(fo.outlier_sigmas * fo.noise)
    dropped: list[int] = []
    while True:
        stats = frame_disagreement(textures, threshold)
        judged = {f: o / n for f, (n, o) in stats.items() if n >= options.min_shared}
        if not judged:
            return dropped
        worst = max(judged, key=lambda f: (judged[f], -f))
        limit = max(options.max_outlier_share, options.relative * float(np.median(list(judged.values()))))
        if judged[worst] <= limit:
            return dropped
        for tex in textures:
            tex.drop_frame(worst)
        dropped.append(worst)
