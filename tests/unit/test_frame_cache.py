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


def test_physical_frames_are_decoded_once_and_handed_out_fresh(tmp_path, monkeypatch) -> None:
    """`PackageFrames.load` decodes a frame once per process (the decoded frame is kept) and
    converts it on every load: the same values each time (NaN where DN 0), as a fresh writable
    array (a caller writing into it changes nothing for the next); another radiometry converts the
    same decoded frame its own way; a rewritten file is read anew."""
    import os

    import cv2

    import db.sequence_package as sp
    from workers.pipeline.geometry.manifest import Radiometry

    monkeypatch.setattr(sp, "_FRAMES", type(sp._FRAMES)())
    monkeypatch.setattr(sp, "_CACHED_BYTES", [0])
    dn = np.random.default_rng(3).integers(1, 40_000, (6, 8)).astype(np.uint16)
    dn[2, 3] = 0
    assert cv2.imwrite(str(tmp_path / "f0.png"), dn)
    rad = Radiometry(scale=0.01, offset=-1.5)
    frames = sp.PackageFrames(str(tmp_path), ("f0.png",), 8, 6, rad)
    calls = []
    real = sp.read_frame_raw
    monkeypatch.setattr(sp, "read_frame_raw", lambda p, n=None: calls.append(1) or real(p, n))
    first = frames.load(0)
    expect = dn.astype(np.float32) * np.float32(0.01) + np.float32(-1.5)
    expect[2, 3] = np.nan
    np.testing.assert_array_equal(first, expect)
    first[:] = 0.0  # the caller owns its array
    second = frames.load(0)
    np.testing.assert_array_equal(second, expect)
    assert second.flags.writeable and len(calls) == 1
    other = sp.PackageFrames(str(tmp_path), ("f0.png",), 8, 6, Radiometry(scale=0.02)).load(0)
    assert np.isnan(other[2, 3]) and other[0, 0] == np.float32(dn[0, 0]) * np.float32(0.02)
    assert len(calls) == 1  # the same file: decoded once
    assert cv2.imwrite(str(tmp_path / "f0.png"), dn + 1)
    os.utime(tmp_path / "f0.png", ns=(1, 1))  # a new modification time: a new cache key
    np.testing.assert_allclose(frames.load(0)[0, 0], expect[0, 0] + 0.01, rtol=1e-5)
    assert len(calls) == 2


def test_dn_table_converts_every_dn_as_the_radiometry_does() -> None:
    """The 16-bit conversion by table (`dn_table`) equals `Radiometry.physical` bit for bit for
    every DN but 0 (NaN: not observed), and the table cannot be written."""
    import pytest

    import db.sequence_package as sp
    from workers.pipeline.geometry.manifest import Radiometry

    dn = np.arange(65536, dtype=np.uint16)
    for rad in (Radiometry(scale=0.01, offset=-1.5), Radiometry(scale=0.04, offset=200.0)):
        got = sp.physical_from_raw(dn.reshape(256, 256), rad).ravel()
        direct = rad.physical(dn)
        np.testing.assert_array_equal(got[1:].view(np.uint32), direct[1:].view(np.uint32))
        assert np.isnan(got[0]) and got.flags.writeable
        with pytest.raises(ValueError):
            sp.dn_table(rad)[1] = 0.0
