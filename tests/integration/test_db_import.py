"""Import of every real CityGML sample into PostGIS: counts equal the reader's, geometries valid
with the model SRID, 3D coordinates round-trip, appearances and checks stored, re-import refused
unless replaced, a failed import leaves nothing; bbox export selects by envelope."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import text

import db.importer as importer_mod
from db.citygml.names import CityGMLError
from db.citygml.reader import read_model
from db.citygml.validate import validate_citygml2
from db.errors import InputDataError, ModelExistsError
from db.export import export_citygml
from db.geomcodec import polygon_rings_from_wkb
from db.importer import ImportOptions, import_citygml
from tests.conftest import DATA, SAMPLE_FILES
from tests.integration.conftest import TEST_SRID
from workers.pipeline.geometry.crs import horizontal_epsg
from workers.pipeline.geometry.transform import CrsTransform
from workers.pipeline.synth import BUNDLED_MODEL

pytestmark = pytest.mark.integration


def _scalar(engine, sql: str, **p):
    with engine.connect() as c:
        return c.execute(text(sql), p).scalar_one()


@pytest.mark.parametrize("path", SAMPLE_FILES, ids=[p.stem for p in SAMPLE_FILES])
def test_import_sample(db_engine, path: Path) -> None:
    header, buildings = read_model(path)
    name = f"imp-{path.stem}"
    s = import_citygml(db_engine, path, name=name, options=ImportOptions(batch_size=40))
    flat = [b for t in buildings for b in t.iter_buildings()]
    polys = [p for b in flat for p in b.polygons]
    assert s.buildings == len(buildings)
    assert s.parts == sum(b.is_part for b in flat)
    assert s.surfaces == len(polys)
    assert s.srid == horizontal_epsg(header.srs_name) > 0
    with db_engine.connect() as c:
        m = s.model_id
        n_b, n_p = c.execute(
            text(
                "SELECT count(*) FILTER (WHERE NOT is_part), count(*) FILTER (WHERE is_part) FROM building "
                "WHERE city_model_id = :m"
            ),
            {"m": m},
        ).one()
        assert (n_b, n_p) == (s.buildings, s.parts)
        # parts point to an existing parent of the same model; roots are top-level buildings
        orphans = c.execute(
            text(
                "SELECT count(*) FROM building b LEFT JOIN building p ON p.id = b.parent_id "
                "WHERE b.city_model_id = :m AND b.is_part AND (p.id IS NULL OR p.city_model_id <> :m)"
            ),
            {"m": m},
        ).scalar_one()
        assert orphans == 0
        srids = (
            c.execute(
                text(
                    "SELECT DISTINCT ST_SRID(geometry) FROM surface WHERE city_model_id = :m UNION "
                    "SELECT DISTINCT ST_SRID(footprint) FROM building "
                    "WHERE city_model_id = :m AND footprint IS NOT NULL "
                    "UNION SELECT DISTINCT ST_SRID(envelope) FROM building WHERE city_model_id = :m"
                ),
                {"m": m},
            )
            .scalars()
            .all()
        )
        assert set(srids) == {TEST_SRID}  # the database's, whatever the model's own CRS
        invalid_fp = c.execute(
            text("SELECT count(*) FROM building WHERE city_model_id = :m AND NOT ST_IsValid(footprint)"),
            {"m": m},
        ).scalar_one()
        assert invalid_fp == 0
        no_fp = c.execute(
            text(
                "SELECT count(*) FROM building WHERE city_model_id = :m AND NOT is_part AND footprint IS NULL"
            ),
            {"m": m},
        ).scalar_one()
        assert no_fp == 0
        rows = c.execute(
            text(
                "SELECT b.gml_id, s.gml_id, ST_AsBinary(s.geometry), s.ring_ids, s.ring_closed "
                "FROM surface s JOIN building b ON b.id = s.building_id "
                "WHERE s.city_model_id = :m ORDER BY b.ordinal, s.ordinal"
            ),
            {"m": m},
        ).all()
        # horizontal polygons without reported problems are valid in PostGIS (2D validity applies)
        bad = c.execute(
            text(
                "SELECT count(*) FROM surface WHERE city_model_id = :m AND abs(plane_normal[3]) > 0.99 "
                "AND jsonb_array_length(checks->'problems') = 0 AND NOT ST_IsValid(geometry)"
            ),
            {"m": m},
        ).scalar_one()
        assert bad == 0
    assert [(r[0], r[1]) for r in rows] == [(b.id, p.id) for b in flat for p in b.polygons]
    worst = 0.0
    to_db = CrsTransform(header.srs_name, f"EPSG:{TEST_SRID}")  # stored in the database SRID
    for r, p in zip(rows, polys, strict=True):
        rings = polygon_rings_from_wkb(r[2])
        assert list(r[3]) == [x.id for x in p.rings]
        for got, ring, closed in zip(rings, p.rings, r[4], strict=True):
            got = got if closed else got[:-1]
            assert got.shape == ring.coords.shape
            worst = max(worst, float(np.max(np.abs(got - to_db.points(ring.coords)))))
    assert worst <= 1e-6


def test_appearances_of_the_file_are_imported(db_engine, tmp_path) -> None:
    path = DATA / "berlin-moabit-textured-citygml2-lod2.gml"
    _, buildings = read_model(path)
    apps = [a for t in buildings for b in t.iter_buildings() for a in b.appearances]
    assert len({a.theme for a in apps}) == 3
    s = import_citygml(db_engine, path, name="apps-moabit")
    assert s.appearances == len(apps)
    with db_engine.connect() as c:
        themes = c.execute(
            text("SELECT theme, count(*) FROM appearance WHERE city_model_id = :m GROUP BY theme"),
            {"m": s.model_id},
        ).all()
        assert dict(themes) == {t: sum(a.theme == t for a in apps) for t in {a.theme for a in apps}}
        n_targets = c.execute(
            text(
                "SELECT count(*), count(tp.surface_id) FROM texture_param tp JOIN surface_data sd "
                "ON sd.id = tp.surface_data_id JOIN appearance a ON a.id = sd.appearance_id "
                "WHERE a.city_model_id = :m"
            ),
            {"m": s.model_id},
        ).one()
    expected = sum(len(sd.targets) for a in apps for sd in a.surface_data)
    assert n_targets[0] == expected and n_targets[1] > 0
    # export writes them back: same themes and targets, valid CityGML 2.0
    out = export_citygml(db_engine, tmp_path, model="apps-moabit")
    assert validate_citygml2(out.path) == []
    _, back = read_model(out.path)
    back_apps = [a for t in back for b in t.iter_buildings() for a in b.appearances]
    assert sorted(a.theme for a in back_apps) == sorted(a.theme for a in apps)
    assert sum(len(sd.targets) for a in back_apps for sd in a.surface_data) == expected


def test_reimport_refused_unless_replace_and_full_checks(db_engine) -> None:
    path = DATA / "bavaria-1-building-citygml2-lod2.gml"
    first = import_citygml(db_engine, path, name="re-bavaria")
    with pytest.raises(ModelExistsError):
        import_citygml(db_engine, path, name="re-bavaria")
    second = import_citygml(
        db_engine, path, name="re-bavaria", replace=True, options=ImportOptions(checks="full")
    )
    assert second.replaced and second.model_id != first.model_id
    assert _scalar(db_engine, "SELECT count(*) FROM city_model WHERE name = 're-bavaria'") == 1
    assert _scalar(db_engine, "SELECT count(*) FROM building WHERE city_model_id = :m", m=first.model_id) == 0
    assert (
        _scalar(db_engine, "SELECT count(*) FROM surface WHERE city_model_id = :m", m=second.model_id) == 84
    )
    levels = _scalar(
        db_engine,
        "SELECT array_agg(DISTINCT checks->>'level') FROM surface WHERE city_model_id = :m",
        m=second.model_id,
    )
    assert levels == ["full"]
    walls = _scalar(
        db_engine,
        "SELECT count(*) FROM surface WHERE city_model_id = :m AND surface_class = 'WallSurface' "
        "AND checks ? 'normal_outward'",
        m=second.model_id,
    )
    assert walls > 0


def test_failed_import_leaves_nothing(db_engine, monkeypatch) -> None:
    path = BUNDLED_MODEL
    real = importer_mod._write_lines
    calls = {"n": 0}

    def failing(conn, lines, model_id, ordinal0, **kw):
        calls["n"] += 1
        real(conn, lines, model_id, ordinal0, **kw)
        if calls["n"] == 2:
            raise RuntimeError("disk full (simulated)")

    monkeypatch.setattr(importer_mod, "_write_lines", failing)
    before = _scalar(db_engine, "SELECT count(*) FROM building")
    with pytest.raises(RuntimeError, match="simulated"):
        import_citygml(db_engine, path, name="fails", options=ImportOptions(batch_size=20))
    assert calls["n"] == 2
    assert _scalar(db_engine, "SELECT count(*) FROM city_model WHERE name = 'fails'") == 0
    assert _scalar(db_engine, "SELECT count(*) FROM building") == before
    # a failed replacement leaves the old model as it was
    monkeypatch.setattr(importer_mod, "_write_lines", real)
    old = import_citygml(db_engine, path, name="fails-replace")
    calls["n"] = 0
    monkeypatch.setattr(importer_mod, "_write_lines", failing)
    with pytest.raises(RuntimeError, match="simulated"):
        import_citygml(
            db_engine, path, name="fails-replace", replace=True, options=ImportOptions(batch_size=20)
        )
    assert _scalar(db_engine, "SELECT count(*) FROM city_model WHERE name LIKE 'fails-replace%'") == 1
    assert _scalar(db_engine, "SELECT count(*) FROM building WHERE city_model_id = :m", m=old.model_id) == 61


def test_spatial_indexes_kept_and_bbox_export(db_engine, tmp_path) -> None:
    path = BUNDLED_MODEL
    s = import_citygml(db_engine, path, name="bbox-berlin", options=ImportOptions(batch_size=25))
    with db_engine.connect() as c:
        idx = set(
            c.execute(
                text(
                    "SELECT c.relname FROM pg_index i JOIN pg_class c ON c.oid = i.indexrelid "
                    "WHERE i.indrelid IN ('building'::regclass, 'surface'::regclass) AND i.indisvalid"
                )
            ).scalars()
        )
        assert {"ix_building_footprint", "ix_building_envelope", "ix_surface_geometry"} <= idx
        x0, y0, x1, y1 = c.execute(
            text(
                "SELECT ST_XMin(e), ST_YMin(e), ST_XMax(e), ST_YMax(e) FROM (SELECT ST_Extent(envelope) e "
                "FROM building WHERE city_model_id = :m) q"
            ),
            {"m": s.model_id},
        ).one()
        box = (x0, y0, (x0 + x1) / 2, (y0 + y1) / 2)
        expected = (
            c.execute(
                text(
                    "SELECT gml_id FROM building WHERE city_model_id = :m AND NOT is_part "
                    "AND envelope && ST_MakeEnvelope(:a, :b, :c, :d, :srid) ORDER BY ordinal"
                ),
                {"m": s.model_id, "a": box[0], "b": box[1], "c": box[2], "d": box[3], "srid": TEST_SRID},
            )
            .scalars()
            .all()
        )
    assert 0 < len(expected) < s.buildings
    out = export_citygml(db_engine, tmp_path, model="bbox-berlin", bbox=box)
    _, back = read_model(out.path)
    assert [b.id for b in back] == expected
    assert validate_citygml2(out.path) == []


def test_parallel_reader_writes_the_same_rows(db_engine, tmp_path) -> None:
    path = DATA / "nrw-tile-5659-citygml1-lod2.gml"
    seq = import_citygml(
        db_engine, path, name="par-seq", options=ImportOptions(parallel_read=False, batch_size=30)
    )
    par = import_citygml(
        db_engine, path, name="par-fork", options=ImportOptions(parallel_read=True, batch_size=30)
    )
    assert (par.buildings, par.parts, par.surfaces) == (seq.buildings, seq.parts, seq.surfaces)
    assert par.reader_peak_rss_mb is not None and seq.reader_peak_rss_mb is None
    sql = (
        "SELECT b.gml_id, b.ordinal, p.gml_id, s.gml_id, s.ordinal, ST_AsBinary(s.geometry), s.ring_ids, "
        "s.checks "
        "FROM surface s JOIN building b ON b.id = s.building_id LEFT JOIN building p ON p.id = b.parent_id "
        "WHERE s.city_model_id = :m ORDER BY b.ordinal, s.ordinal"
    )
    with db_engine.connect() as c:
        rows_seq = c.execute(text(sql), {"m": seq.model_id}).all()
        rows_par = c.execute(text(sql), {"m": par.model_id}).all()
    assert len(rows_seq) == seq.surfaces and rows_par == rows_seq
    # a broken file: the reader process's error arrives here and nothing is left
    broken = tmp_path / "broken.gml"
    data = path.read_bytes()
    broken.write_bytes(data[: len(data) // 2] + b"<bldg:Building><oops></core:CityModel>")
    with pytest.raises(CityGMLError):
        import_citygml(db_engine, broken, name="par-broken", options=ImportOptions(parallel_read=True))
    assert _scalar(db_engine, "SELECT count(*) FROM city_model WHERE name = 'par-broken'") == 0


def test_duplicate_building_ids_refused_by_name(db_engine, tmp_path) -> None:
    data = (DATA / "bavaria-1-building-citygml2-lod2.gml").read_text(encoding="utf-8")
    start = data.index("<core:cityObjectMember>")
    end = data.index("</core:cityObjectMember>") + len("</core:cityObjectMember>")
    twice = tmp_path / "twice.gml"
    twice.write_text(data[:end] + "\n" + data[start:end] + data[end:], encoding="utf-8")
    with pytest.raises(InputDataError, match=r"twice\.gml.*uq_building_model_gml_id"):
        import_citygml(db_engine, twice, name="twice")
    assert _scalar(db_engine, "SELECT count(*) FROM city_model WHERE name = 'twice'") == 0


def test_texture_images_next_to_the_file_are_imported(db_engine, tmp_path) -> None:
    """The Moabit sample with its (here: generated) texture files: images stored once per
    appearance and URI, exported byte for byte; a URI escaping the folder is never read."""
    import re

    import cv2

    src = (DATA / "berlin-moabit-textured-citygml2-lod2.gml").read_text(encoding="utf-8")
    uris = sorted(set(re.findall(r"<app:imageURI>([^<]*)</app:imageURI>", src)))
    assert len(uris) == 5
    folder = tmp_path / "in"
    rng = np.random.default_rng(5)
    for k, uri in enumerate(uris):
        (folder / uri).parent.mkdir(parents=True, exist_ok=True)
        img = rng.integers(0, 255, (8 + k, 12, 3), dtype=np.uint8)
        assert cv2.imwrite(str(folder / uri), img)
    # one URI pointing outside the folder: must be left alone
    (tmp_path / "secret.jpg").write_bytes((folder / uris[0]).read_bytes())
    gml = folder / "moabit.gml"
    gml.write_text(src.replace(uris[0], "../secret.jpg"), encoding="utf-8")
    s = import_citygml(db_engine, gml, name="moabit-images")
    with db_engine.connect() as c:
        rows = c.execute(
            text(
                "SELECT ti.uri, ti.mime_type, ti.width, ti.height, ti.bit_depth FROM tex_image ti "
                "JOIN appearance a ON a.id = ti.appearance_id WHERE a.city_model_id = :m ORDER BY ti.uri"
            ),
            {"m": s.model_id},
        ).all()
        linked = c.execute(
            text(
                "SELECT count(*) FROM surface_data sd JOIN appearance a ON a.id = sd.appearance_id "
                "WHERE a.city_model_id = :m AND sd.tex_image_id IS NOT NULL"
            ),
            {"m": s.model_id},
        ).scalar_one()
    # images are owned by their appearance: one row per (appearance, URI) whose file is inside
    _, back = read_model(gml)
    apps = [a for t in back for b in t.iter_buildings() for a in b.appearances]
    pairs = {
        (k, sd.image_uri) for k, a in enumerate(apps) for sd in a.surface_data if hasattr(sd, "image_uri")
    }
    inside = {p for p in pairs if p[1] != "../secret.jpg"}
    assert len(rows) == len(inside) and {r[0] for r in rows} == set(uris[1:])
    assert all(r[1] == "image/jpeg" and r[4] == 8 for r in rows)
    assert {(r[0], r[2], r[3]) for r in rows} == {(u, 12, 8 + k) for k, u in enumerate(uris) if k > 0}
    n_sd = sum(
        1
        for a in apps
        for sd in a.surface_data
        if getattr(sd, "image_uri", None) not in (None, "../secret.jpg")
    )
    assert linked == n_sd
    out = export_citygml(db_engine, tmp_path / "out", model="moabit-images")
    assert out.textures == 4 and validate_citygml2(out.path) == []
    for uri in uris[1:]:
        assert (tmp_path / "out" / uri).read_bytes() == (folder / uri).read_bytes()


def test_two_readers_and_unchecked_own_links_write_the_same_rows(db_engine) -> None:
    """Two reader processes (one per half of the file) and the foreign keys of the copied rows
    left unchecked (the test role may set `session_replication_role`) give the rows of one reader
    with every check; the final step checks and cascades again: a replacement takes the surface
    data of the old model's appearances with it."""
    path = DATA / "nrw-tile-5659-citygml1-lod2.gml"
    checked = ImportOptions(parallel_read=False, own_links_unchecked=False, batch_size=30)
    plain = import_citygml(db_engine, path, name="split-plain", options=checked)
    fast_opts = ImportOptions(parallel_read=True, split_above_bytes=1, batch_size=30)
    fast = import_citygml(db_engine, path, name="split-fast", options=fast_opts)
    assert len(fast.reader_cpu_s) == 2 and plain.reader_cpu_s == ()
    sql = (
        "SELECT b.gml_id, b.ordinal, b.is_part, p.gml_id, r.gml_id, b.attributes, ST_AsBinary(b.footprint), "
        "ST_AsBinary(b.envelope), s.gml_id, s.ordinal, ST_AsBinary(s.geometry), s.ring_ids, s.checks "
        "FROM surface s JOIN building b ON b.id = s.building_id JOIN building r ON r.id = b.root_id "
        "LEFT JOIN building p ON p.id = b.parent_id WHERE s.city_model_id = :m ORDER BY b.ordinal, s.ordinal"
    )
    with db_engine.connect() as c:
        assert importer_mod._may_skip_link_checks(c)
        rows = [c.execute(text(sql), {"m": m}).all() for m in (plain.model_id, fast.model_id)]
    assert len(rows[0]) == plain.surfaces and rows[1] == rows[0]
    berlin = DATA / "berlin-moabit-textured-citygml2-lod2.gml"
    first = import_citygml(db_engine, berlin, name="split-berlin")
    n_data = _scalar(
        db_engine,
        "SELECT count(*) FROM surface_data sd JOIN appearance a ON a.id = sd.appearance_id "
        "WHERE a.city_model_id = :m",
        m=first.model_id,
    )
    assert n_data > 0
    import_citygml(db_engine, berlin, name="split-berlin", replace=True)
    orphans = (
        "SELECT count(*) FROM surface_data sd "
        "WHERE NOT EXISTS (SELECT 1 FROM appearance a WHERE a.id = sd.appearance_id)"
    )
    assert _scalar(db_engine, orphans) == 0


@pytest.mark.parametrize(
    ("old", "new"),
    [
        # a value that looks like a building start tag: the first part's count is one too high
        (b"<gen:value>1000</gen:value>", b"<gen:value>Building 1000</gen:value>"),
        # a part without gml:id (its generated id does not count buildings): one too low
        (b'<bldg:BuildingPart gml:id="', b"<bldg:BuildingPart>"),
    ],
    ids=["estimate-high", "estimate-low"],
)
def test_split_import_numbers_the_second_part_right_when_the_estimate_is_wrong(
    db_engine, tmp_path, request, old, new
) -> None:
    """The second part's buildings are written while the first part is still being read,
    numbered after the first part's count estimated from its bytes; where that estimate is wrong
    the import renumbers them: the rows are those of one reader."""
    from tests.conftest import replicated_nrw

    src = replicated_nrw(tmp_path / "nrw-3.gml", 3).read_bytes()
    k = src.index(old)
    assert k < len(src) // 3  # in the first part
    # the edit ends at the end of the start tag when it removes the part's attribute
    end = src.index(b">", k) + 1 if new.endswith(b"Part>") else k + len(old)
    path = tmp_path / "edited.gml"
    path.write_bytes(src[:k] + new + src[end:])
    case = request.node.callspec.id
    one_opts = ImportOptions(parallel_read=False, batch_size=20)
    one = import_citygml(db_engine, path, name=f"one-{case}", options=one_opts)
    two = import_citygml(
        db_engine,
        path,
        name=f"two-{case}",
        options=ImportOptions(parallel_read=True, split_above_bytes=1, batch_size=20),
    )
    assert len(two.reader_cpu_s) == 2 and one.reader_cpu_s == ()
    sql = (
        "SELECT b.gml_id, b.ordinal, b.is_part, p.gml_id, r.gml_id, b.attributes, s.gml_id, s.ordinal "
        "FROM surface s JOIN building b ON b.id = s.building_id JOIN building r ON r.id = b.root_id "
        "LEFT JOIN building p ON p.id = b.parent_id WHERE s.city_model_id = :m ORDER BY b.ordinal, s.ordinal"
    )
    with db_engine.connect() as c:
        rows = [c.execute(text(sql), {"m": m}).all() for m in (one.model_id, two.model_id)]
        ordinals = c.execute(
            text("SELECT array_agg(ordinal ORDER BY ordinal) FROM building WHERE city_model_id = :m"),
            {"m": two.model_id},
        ).scalar_one()
    assert len(rows[0]) == one.surfaces and rows[1] == rows[0]
    assert ordinals == list(range(one.buildings + one.parts))


def test_foreign_keys_are_unchecked_only_where_allowed_and_no_trigger_is(db_engine, migrated_db) -> None:
    """`session_replication_role` is set only by a role that may (a superuser, or one granted SET
    on it) and only while the schema has no trigger of its own (replica mode would skip it)."""
    import psycopg
    from sqlalchemy import create_engine
    from sqlalchemy.engine import make_url

    from db.session import sqlalchemy_url

    role = "citytherm_test_import_role"
    with psycopg.connect(migrated_db, autocommit=True) as c:
        c.execute(f"DROP ROLE IF EXISTS {role}")
        c.execute(f"CREATE ROLE {role} LOGIN")
    plain = create_engine(make_url(sqlalchemy_url(migrated_db)).set(username=role))
    try:
        with plain.connect() as c:
            assert not importer_mod._may_skip_link_checks(c)
        with psycopg.connect(migrated_db, autocommit=True) as c:
            c.execute(f"GRANT SET ON PARAMETER session_replication_role TO {role}")
        with plain.connect() as c:
            assert importer_mod._may_skip_link_checks(c)
        with db_engine.connect() as c:  # a trigger of the schema's own: replica mode for nobody
            assert importer_mod._may_skip_link_checks(c)
            c.execute(
                text("CREATE FUNCTION noop() RETURNS trigger LANGUAGE plpgsql AS 'BEGIN RETURN NEW; END'")
            )
            c.execute(
                text("CREATE TRIGGER audit AFTER INSERT ON surface FOR EACH ROW EXECUTE FUNCTION noop()")
            )
            assert not importer_mod._may_skip_link_checks(c)
            c.rollback()
    finally:
        plain.dispose()
        with psycopg.connect(migrated_db, autocommit=True) as c:
            c.execute(f"REVOKE SET ON PARAMETER session_replication_role FROM {role}")
            c.execute(f"DROP ROLE {role}")
