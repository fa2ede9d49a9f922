"""The decoded-frame cache of the sequence package reader (`db.sequence_package`)."""

from __future__ import annotations

import numpy as np


def test_frame_cache_keeps_its_byte_total_and_bound(monkeypatch) -> None:
    """The decoded-frame cache keeps a running byte total (no sum over the cache per insert):
    it equals the frames held, stays within `FRAME_CACHE_BYTES`, and a frame stored again is
    counted once; the least recently stored go first."""
    import db.sequence_package as sp

    monkeypatch.setattr(sp, "FRAME_CACHE_BYTES", 10_000)
    monkeypatch.setattr(sp, "_FRAMES", type(sp._FRAMES)())
    monkeypatch.setattr(sp, "_CACHED_BYTES", [0])
    for i in range(50):
        sp._remember(("pkg", i, 0), np.zeros(100, np.float32))  # 400 bytes each
        sp._remember(("pkg", i % 3, 0), np.zeros(100, np.float32))
        assert sp._CACHED_BYTES[0] == sum(a.nbytes for a in sp._FRAMES.values()) <= 10_000
    assert len(sp._FRAMES) == 25 and ("pkg", 49, 0) in sp._FRAMES and ("pkg", 10, 0) not in sp._FRAMES
