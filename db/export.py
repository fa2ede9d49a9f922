"""Export a city model (or part of it) from the database as CityGML 2.0 plus texture files, in the
results format (`docs/results-format.md`: `textured.gml`, `textures/*.png`).

In: a database (Engine, sessionmaker or URL), a model (name or id), optionally a theme, a job and a
2D bbox in the model CRS. Out: `OUT/textured.gml` written by `db.citygml.writer.write_citygml`
from `Building` and `Appearance` dataclasses rebuilt from the rows (ids, ring ids, coordinates
bit-exact, texture coordinates exact), `OUT/<imageURI>` for every stored texture image, and
`OUT/anomalies.geojson` with the exported jobs' heat-leak candidates.

Streamed: the top-level building ids are listed first (one integer each), then buildings are
fetched in batches of `ExportOptions.batch_size` and handed to the writer one by one, so memory
does not grow with the model. Each building's appearances are those imported with the file, then
the jobs' (the order in which the writer puts a building's own and its `extra_appearances`, so the
output equals the in-process `textured.gml`). With a
theme only that theme's appearances are written, and only buildings that have one.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from os import PathLike
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
from sqlalchemy import Connection, Engine, text

from db.appearance_rows import load_texture_params, surface_data_from_rows
from db.citygml.writer import write_citygml
from db.errors import CityDBError, NotFoundError
from db.model_load import assemble_buildings, building_rows, surface_polygons
from db.result_load import anomaly_from_row, from_kelvin
from db.results_folder.write import anomalies_document, anomaly_feature, facade_attributes, write_json
from db.session import as_engine
from db.srid import database_srid, from_database
from workers.pipeline.geometry.citymodel import Appearance, Building, ParameterizedTexture
from workers.pipeline.geometry.transform import CrsTransform, transform_building

__all__ = ["ExportOptions", "ExportSummary", "export_citygml"]


@dataclass(frozen=True)
class ExportOptions:
    """Options of `export_citygml`.

    Attributes:
        batch_size: top-level buildings fetched per query round.
        gml_name: file name of the CityGML document inside the output folder.
        include_imported: also write the appearances imported with the file (when no theme is
            given, or when they have the requested theme).
    """

    batch_size: int = 200
    gml_name: str = "textured.gml"
    include_imported: bool = True


@dataclass(frozen=True)
class ExportSummary:
    """What an export wrote."""

    path: Path
    buildings: int
    textures: int
    seconds: float
    anomalies: int = 0


@dataclass(frozen=True)
class _Filter:
    model_id: int
    theme: str | None
    job_id: Any
    bbox: tuple[float, float, float, float] | None
    srid: int
    include_imported: bool
    db_srid: int = 0

    def appearance_sql(self, alias: str = "a") -> str:
        """SQL condition selecting the exported appearances."""
        cond = []
        if self.theme is not None:
            cond.append(f"{alias}.theme = :theme")
        if self.job_id is not None:
            cond.append(f"({alias}.job_id = :job OR {alias}.job_id IS NULL)")
        if not self.include_imported:
            cond.append(f"{alias}.job_id IS NOT NULL")
        return " AND ".join(cond) if cond else "TRUE"

    def params(self) -> dict[str, Any]:
        p: dict[str, Any] = {"m": self.model_id, "theme": self.theme, "job": self.job_id}
        p.update(srid=self.srid, db_srid=self.db_srid)
        if self.bbox is not None:
            p.update(dict(zip(("x0", "y0", "x1", "y1"), self.bbox, strict=True)))
        return p

    def building_sql(self) -> str:
        """SQL selecting the exported top-level buildings (alias `b`): with a theme or job, those
        with a non-empty appearance of it (the buildings the job textured)."""
        sql = "SELECT b.id FROM building b WHERE b.city_model_id = :m AND NOT b.is_part"
        if self.bbox is not None:
            # the box is in the model's CRS, the envelopes in the database SRID
            sql += " AND b.envelope && ST_Transform(ST_MakeEnvelope(:x0, :y0, :x1, :y1, :srid), :db_srid)"
        if self.theme is not None or self.job_id is not None:
            sql += (
                " AND EXISTS (SELECT 1 FROM appearance a JOIN building pb ON pb.id = a.building_id"
                " JOIN surface_data sd ON sd.appearance_id = a.id"
                f" WHERE pb.root_id = b.id AND {self.appearance_sql()})"
            )
        return sql


def _model(conn: Connection, model: str | int) -> Mapping[str, Any]:
    col = "id" if isinstance(model, int) or str(model).isdigit() else "name"
    row = (
        conn.execute(
            text(f"SELECT id, name, srs_name, srid, gml_name FROM city_model WHERE {col} = :v"),
            {"v": int(model) if col == "id" else model},
        )
        .mappings()
        .first()
    )
    if row is None:
        raise NotFoundError(f"city model {model!r} not found")
    return row


def _extent(conn: Connection, f: _Filter) -> tuple[np.ndarray, np.ndarray] | None:
    row = conn.execute(
        text(
            "SELECT ST_XMin(e), ST_YMin(e), ST_ZMin(e), ST_XMax(e), ST_YMax(e), ST_ZMax(e) FROM "
            f"(SELECT ST_3DExtent(x.envelope) AS e FROM building x WHERE x.id IN ({f.building_sql()})) q"
        ),
        f.params(),
    ).one()
    if row[0] is None:
        return None
    return np.array(row[:3], dtype=np.float64), np.array(row[3:], dtype=np.float64)


def _safe_uri(uri: str) -> str:
    """A relative POSIX path inside the output folder, or raise."""
    p = PurePosixPath(uri)
    if p.is_absolute() or ".." in p.parts or not p.parts or ":" in p.parts[0]:
        raise CityDBError(f"texture imageURI {uri!r} is not a relative path inside the results folder")
    return str(p)


class _Images:
    """Writes texture images once each; a different image under a URI already taken gets a
    unique URI (`<stem>_<image id><suffix>`)."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.reserved: dict[str, str] = {}  # uri -> sha256 of the image placed there
        self.written: set[str] = set()
        self.count = 0

    def place(self, uri: str, sha: str, image_id: int) -> str:
        """URI to write image `image_id` with checksum `sha` under (the stored one if free)."""
        uri = _safe_uri(uri)
        if self.reserved.setdefault(uri, sha) != sha:
            p = PurePosixPath(uri)
            uri = str(p.with_name(f"{p.stem}_{image_id}{p.suffix}"))
            self.reserved[uri] = sha
        return uri

    def write(self, uri: str, data: bytes) -> None:
        """Write the bytes of a placed image (once)."""
        if uri in self.written:
            return
        path = self.out / uri
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        self.written.add(uri)
        self.count += 1


def _appearances(
    conn: Connection, f: _Filter, building_rows: Sequence[int], images: _Images
) -> tuple[dict[int, list[Appearance]], dict[int, list[Appearance]]]:
    """(imported appearances by building row, job appearances by building row)."""
    p = {**f.params(), "bids": list(building_rows)}
    apps = (
        conn.execute(
            text(
                "SELECT a.id, a.building_id, a.job_id, a.theme, a.gml_id FROM appearance a "
                f"WHERE a.building_id = ANY(:bids) AND {f.appearance_sql()} "
                "ORDER BY a.building_id, a.job_id NULLS FIRST, a.ordinal, a.id"
            ),
            p,
        )
        .mappings()
        .all()
    )
    return _assemble(conn, apps, images)


def _assemble(
    conn: Connection, apps: Sequence[Mapping[str, Any]], images: _Images
) -> tuple[dict[int, list[Appearance]], dict[int, list[Appearance]]]:
    own: dict[int, list[Appearance]] = defaultdict(list)
    extra: dict[int, list[Appearance]] = defaultdict(list)
    if not apps:
        return own, extra
    aids = [a["id"] for a in apps]
    sds = (
        conn.execute(
            text(
                "SELECT sd.*, ti.sha256 AS tex_sha FROM surface_data sd LEFT JOIN tex_image ti "
                "ON ti.id = sd.tex_image_id WHERE sd.appearance_id = ANY(:a) "
                "ORDER BY sd.appearance_id, sd.ordinal"
            ),
            {"a": aids},
        )
        .mappings()
        .all()
    )
    params = load_texture_params(conn, [sd["id"] for sd in sds])
    wanted: dict[int, list[str]] = defaultdict(list)
    by_app: dict[int, list[Any]] = defaultdict(list)
    for sd in sds:
        data = surface_data_from_rows(sd, params.get(sd["id"], []))
        if sd["tex_image_id"] is not None and isinstance(data, ParameterizedTexture):
            uri = images.place(data.image_uri, sd["tex_sha"], sd["tex_image_id"])
            wanted[sd["tex_image_id"]].append(uri)
            if uri != data.image_uri:
                data = replace(data, image_uri=uri)
        by_app[sd["appearance_id"]].append(data)
    if wanted:
        for iid, blob in conn.execute(
            text("SELECT id, image FROM tex_image WHERE id = ANY(:i)"), {"i": list(wanted)}
        ).all():
            for uri in wanted[iid]:
                images.write(uri, bytes(blob))
    for a in apps:
        sd_list = by_app.get(a["id"], [])
        if not sd_list:
            continue
        app = Appearance(theme=a["theme"], surface_data=tuple(sd_list), id=a["gml_id"])
        (own if a["job_id"] is None else extra)[a["building_id"]].append(app)
    return own, extra


def _batch(
    conn: Connection,
    f: _Filter,
    roots: Sequence[int],
    images: _Images,
) -> list[Building]:
    """Rebuild the top-level buildings `roots` (parts nested) with their appearances."""
    brows = building_rows(conn, roots)
    bids = [b["id"] for b in brows]
    polys = surface_polygons(conn, bids)
    own, extra = _appearances(conn, f, bids, images)
    # the file's own appearances, then the jobs' (the writer's order for extra appearances)
    return assemble_buildings(roots, brows, polys, lambda bid: (*own.get(bid, ()), *extra.get(bid, ())))


def export_citygml(
    db: Engine | Any,
    out_dir: str | PathLike[str],
    *,
    model: str | int,
    theme: str | None = None,
    job_id: Any = None,
    bbox: tuple[float, float, float, float] | None = None,
    options: ExportOptions | None = None,
) -> ExportSummary:
    """Write `out_dir/textured.gml` and `out_dir/textures/...` for a model (name or id).

    `theme` keeps that theme's appearances only (and the buildings that have one); `job_id` keeps
    one job's appearances (plus imported ones); `bbox` = (minx, miny, maxx, maxy) in the model CRS
    keeps the top-level buildings whose 3D envelope meets it. Raises `NotFoundError`.
    """
    opts = options or ExportOptions()
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    engine = as_engine(db)
    images = _Images(out)
    with engine.connect() as conn:
        # many small indexed queries: parallel workers only add start-up time
        conn.exec_driver_sql("SET LOCAL max_parallel_workers_per_gather = 0")
        m = _model(conn, model)
        db_srid = database_srid(conn)
        back = from_database(m["srs_name"], db_srid)
        f = _Filter(
            model_id=m["id"],
            theme=theme,
            job_id=job_id,
            srid=m["srid"],
            db_srid=db_srid,
            include_imported=opts.include_imported,
            bbox=None if bbox is None else tuple(float(v) for v in bbox),  # type: ignore[arg-type]
        )
        roots = [r[0] for r in conn.execute(text(f.building_sql() + " ORDER BY b.ordinal"), f.params()).all()]
        envelope = _extent(conn, f)
        if envelope is not None and not back.identity:  # the box around the corners moved back
            lo, hi = envelope
            corners = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, -1).T
            moved = back.points(corners)
            envelope = moved.min(axis=0), moved.max(axis=0)
        model_apps = (
            conn.execute(
                text(
                    "SELECT a.id, a.building_id, a.job_id, a.theme, a.gml_id FROM appearance a "
                    f"WHERE a.city_model_id = :m AND a.building_id IS NULL AND {f.appearance_sql()} "
                    "ORDER BY a.ordinal, a.id"
                ),
                f.params(),
            )
            .mappings()
            .all()
        )
        own_model, extra_model = _assemble(conn, model_apps, images)

        figures: dict[str, dict[str, Any]] = {}  # filled batch by batch, read as buildings are written

        def stream() -> Iterator[Building]:
            for i in range(0, len(roots), opts.batch_size):
                batch = roots[i : i + opts.batch_size]
                if f.job_id is not None or f.theme is not None:  # as the job's results folder has them
                    figures.update(_facade_figures(conn, f, batch))
                for b in _batch(conn, f, batch, images):
                    yield transform_building(b, back, set_srs=False)

        gml = out / opts.gml_name
        n = write_citygml(
            gml,
            stream(),
            srs_name=m["srs_name"],
            envelope=envelope,
            model_appearances=[*own_model.get(None, []), *extra_model.get(None, [])],  # type: ignore[call-overload]
            name=m["gml_name"],
            surface_attributes=figures,
        )
        n_anomalies = _write_anomalies(conn, f, roots, m["srs_name"], out / "anomalies.geojson", back)
    return ExportSummary(
        path=gml, buildings=n, textures=images.count, seconds=time.perf_counter() - t0, anomalies=n_anomalies
    )


def _facade_figures(conn: Connection, f: _Filter, roots: Sequence[int]) -> dict[str, dict[str, Any]]:
    """The facade figures of the exported job's (or theme's) surfaces under the top-level buildings
    `roots` as generic attributes by polygon gml id (`results_folder.write.facade_attributes`),
    the typical temperature back in the radiometry unit; where several jobs of a theme analysed a
    surface, the newest appearance's figures."""
    leaks: dict[int, list[str]] = {}
    for sid, aid in conn.execute(
        text(
            "SELECT ta.surface_id, ta.anomaly_id FROM thermal_anomaly ta JOIN appearance a "
            f"ON a.id = ta.appearance_id WHERE ta.building_id = ANY(:roots) AND {f.appearance_sql()} "
            "AND ta.kind = 'leak' AND ta.anomaly_id IS NOT NULL ORDER BY ta.id"
        ),
        {**f.params(), "roots": list(roots)},
    ).all():
        leaks.setdefault(sid, []).append(aid)
    out: dict[str, dict[str, Any]] = {}
    for r in conn.execute(
        text(
            "SELECT s.id AS sid, s.gml_id, st.typical_k, st.spread_k, st.hot_share, st.window_share, "
            "st.heat_loss_index, st.windows, st.leaks, st.unit FROM surface_thermal st "
            "JOIN appearance a ON a.id = st.appearance_id JOIN surface s ON s.id = st.surface_id "
            f"JOIN building pb ON pb.id = s.building_id WHERE COALESCE(pb.root_id, pb.id) = ANY(:roots) "
            f"AND a.job_id IS NOT NULL AND {f.appearance_sql()} ORDER BY a.id"
        ),
        {**f.params(), "roots": list(roots)},
    ).mappings():
        fig = {**r, "typical": from_kelvin(r["typical_k"], r["unit"]), "spread": r["spread_k"]}
        attrs = facade_attributes(fig, leaks.get(r["sid"], ()))
        if attrs is not None:
            out[r["gml_id"]] = attrs
    return out


def _write_anomalies(
    conn: Connection, f: _Filter, roots: Sequence[int], srs_name: str | None, path: Path, back: CrsTransform
) -> int:
    """`anomalies.geojson` (results format) for the anomalies of the exported job appearances, in
    the model's CRS (`back`: from the database SRID); written when there are any, or when a theme or
    job was asked for. Returns their number."""
    rows = conn.execute(
        text(
            "SELECT b.gml_id AS building, s.gml_id AS surface, ST_AsBinary(ta.outline) AS outline_wkb, "
            "ta.* FROM thermal_anomaly ta "
            "JOIN appearance a ON a.id = ta.appearance_id JOIN building b ON b.id = ta.building_id "
            "LEFT JOIN surface s ON s.id = ta.surface_id "
            f"WHERE ta.building_id = ANY(:roots) AND {f.appearance_sql()} ORDER BY b.ordinal, ta.id"
        ),
        {**f.params(), "roots": list(roots)},
    ).mappings()
    features = [anomaly_feature(anomaly_from_row(r, r["building"], back)) for r in rows]
    if features or f.theme is not None or f.job_id is not None:
        write_json(path, anomalies_document(features, srs_name))
    return len(features)
