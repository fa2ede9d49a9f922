"""Shared bits of the synthetic scene generator: its exception type and seeded random streams.

In: a seed and a stream name. Out: independent, reproducible `numpy.random.Generator`s, so that
changing one part of a scene (e.g. the trajectory) never changes another (e.g. the textures).
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np


class SynthError(ValueError):
    """Bad input to the synthetic scene generator (the message names the field or file)."""


def rng_for(seed: int, stream: str, *extra: int) -> np.random.Generator:
    """A generator for `stream` (e.g. `"thermal"`, `"errors"`, `"noise"`) derived from `seed`.

    The same `(seed, stream, *extra)` always gives the same sequence of draws.
    """
    key = [int(seed) & 0xFFFFFFFF, zlib.crc32(stream.encode()), *(int(e) & 0xFFFFFFFF for e in extra)]
    return np.random.default_rng(np.random.SeedSequence(key))


#: The real model bundled with the package (Berlin open data, see `data/README.md`).
BUNDLED_MODEL = Path(__file__).resolve().parent / "data" / "berlin-61-buildings-citygml1-lod2.gml"
