"""Procedural city blocks: rows of box buildings with gable roofs, as `citymodel.Building`s.

In: a number of buildings and a seed. Out: LoD2 buildings (walls, gable roofs, ground surface)
in a projected CRS (`EPSG:25832` by default, UTM-sized coordinates so that float precision is
exercised like on real data), exterior rings counter-clockwise seen from outside.

Layout: rows of up to `per_row` houses along a street direction (rotated by a random angle),
rows `row_pitch_m` apart so that a car can drive around any row 8–15 m from its facades.
"""

from __future__ import annotations

import numpy as np

from workers.pipeline.geometry.citymodel import Building, Polygon, Ring
from workers.pipeline.synth.common import SynthError, rng_for

DEFAULT_ORIGIN = (691000.0, 5334000.0, 520.0)
DEFAULT_SRS = "EPSG:25832"


def _ring(rid: str, pts: list[tuple[float, float, float]]) -> Ring:
    c = np.asarray(pts, dtype=np.float64)
    return Ring(id=rid, coords=np.vstack([c, c[:1]]))


def gable_house(
    bid: str,
    length: float,
    depth: float,
    eave: float,
    ridge: float,
    origin: np.ndarray,
    angle_rad: float = 0.0,
    srs_name: str = DEFAULT_SRS,
    storeys: int | None = None,
) -> Building:
    """One house: footprint `length` (along local x) × `depth`, walls up to `eave` and a gable
    roof with its ridge along x at height `ridge` (both above `origin[2]`, metres); rotated by
    `angle_rad` about `origin` (the south-west footprint corner), world coordinates.
    `ridge == eave` gives a flat roof."""
    L, D = float(length), float(depth)
    if L <= 0 or D <= 0 or eave <= 0 or ridge < eave:
        raise SynthError(f"gable_house {bid}: bad dimensions L={L} D={D} eave={eave} ridge={ridge}")
    e, r = float(eave), float(ridge)
    flat = r - e < 1e-9
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    o = np.asarray(origin, dtype=np.float64)

    def w(x: float, y: float, z: float) -> tuple[float, float, float]:
        return (o[0] + c * x - s * y, o[1] + s * x + c * y, o[2] + z)

    faces: list[tuple[str, str, list[tuple[float, float, float]]]] = [
        ("ground", "GroundSurface", [w(0, 0, 0), w(0, D, 0), w(L, D, 0), w(L, 0, 0)]),
        ("wall-s", "WallSurface", [w(0, 0, 0), w(L, 0, 0), w(L, 0, e), w(0, 0, e)]),
        ("wall-n", "WallSurface", [w(L, D, 0), w(0, D, 0), w(0, D, e), w(L, D, e)]),
    ]
    if flat:
        faces += [
            ("wall-w", "WallSurface", [w(0, D, 0), w(0, 0, 0), w(0, 0, e), w(0, D, e)]),
            ("wall-e", "WallSurface", [w(L, 0, 0), w(L, D, 0), w(L, D, e), w(L, 0, e)]),
            ("roof", "RoofSurface", [w(0, 0, e), w(L, 0, e), w(L, D, e), w(0, D, e)]),
        ]
    else:
        faces += [
            ("wall-w", "WallSurface", [w(0, D, 0), w(0, 0, 0), w(0, 0, e), w(0, D / 2, r), w(0, D, e)]),
            ("wall-e", "WallSurface", [w(L, 0, 0), w(L, D, 0), w(L, D, e), w(L, D / 2, r), w(L, 0, e)]),
            ("roof-s", "RoofSurface", [w(0, 0, e), w(L, 0, e), w(L, D / 2, r), w(0, D / 2, r)]),
            ("roof-n", "RoofSurface", [w(L, D, e), w(0, D, e), w(0, D / 2, r), w(L, D / 2, r)]),
        ]
    polys = tuple(
        Polygon(
            id=f"{bid}-{name}",
            exterior=_ring(f"{bid}-{name}-ring", pts),
            surface_class=cls,
            lod=2,
            surface_id=f"{bid}-{name}-surface",
            in_solid=True,
        )
        for name, cls, pts in faces
    )
    attrs: dict[str, object] = {"measuredHeight": r, "roofType": "1000" if flat else "1030"}
    if storeys is not None:
        attrs["storeysAboveGround"] = int(storeys)
    return Building(id=bid, polygons=polys, attributes=attrs, srs_name=srs_name)


def procedural_block(
    n_buildings: int,
    seed: int = 0,
    origin: tuple[float, float, float] = DEFAULT_ORIGIN,
    per_row: int = 5,
    row_pitch_m: float = 45.0,
    srs_name: str = DEFAULT_SRS,
) -> list[Building]:
    """`n_buildings` gable-roofed houses (2–5 storeys, 10–18 m × 8–12 m) in rows of `per_row`,
    3–8 m apart along the row, rows `row_pitch_m` apart, the whole block rotated by a random
    angle about `origin` (model CRS, metres). Ids: `proc-<seed>-<i>`."""
    if n_buildings < 1:
        raise SynthError(f"n_buildings must be >= 1, got {n_buildings}")
    rng = rng_for(seed, "procedural")
    angle = float(rng.uniform(0.0, np.pi / 6))
    c, s = np.cos(angle), np.sin(angle)
    o = np.asarray(origin, dtype=np.float64)
    out: list[Building] = []
    x = 0.0
    for i in range(n_buildings):
        row, k = divmod(i, per_row)
        if k == 0:
            x = 0.0
        L, D = rng.uniform(10.0, 18.0), rng.uniform(8.0, 12.0)
        storeys = int(rng.integers(2, 6))
        eave = storeys * rng.uniform(2.9, 3.2) + rng.uniform(0.2, 0.6)
        ridge = eave + (rng.uniform(2.5, 4.5) if rng.uniform() < 0.85 else 0.0)
        y = row * row_pitch_m + rng.uniform(-1.0, 1.0)
        corner = o + np.array([c * x - s * y, s * x + c * y, 0.0])
        out.append(gable_house(f"proc-{seed}-{i}", L, D, eave, ridge, corner, angle, srs_name, storeys))
        x += L + rng.uniform(3.0, 8.0)
    return out
