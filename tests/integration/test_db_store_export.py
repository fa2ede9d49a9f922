"""Import → store a synthetic texturing result → export: the export equals the in-process
`textured.gml` (ids, coordinates, texture coordinates, image bytes) and validates; two themes stay
apart; storing is idempotent and a failure half way leaves nothing partial; the GIS views."""

from __future__ import annotations

import hashlib
import json
import uuid
from pathlib import Path

import cv2
import numpy as np
import pytest
from lxml import etree
from sqlalchemy import text
from sqlalchemy.orm import Session

import db.store as store_mod
from db.citygml.reader import read_model
from db.citygml.validate import validate_citygml2
from db.errors import InputDataError
from db.export import export_citygml
from db.importer import import_citygml
from db.results_folder.write import write_textured_gml, write_tile
from db.store import create_job, store_building_result
from tests.conftest import DATA
from tests.integration.conftest import TEST_SRID
from workers.pipeline.geometry.citymodel import Appearance, Building, ParameterizedTexture, TextureTarget
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.results import Anomaly, BuildingResult, FramePose, SurfaceStats, TextureTile

pytestmark = pytest.mark.integration

SAMPLE = DATA / "bavaria-1-building-citygml2-lod2.gml"
TEXTURED = 6  # polygons given a texture


def make_result(building: Building, theme: str, seed: int, radiometry: Radiometry) -> BuildingResult:
    """A hand-made unit result: two tiles, texture coordinates for the first TEXTURED walls."""
    rng = np.random.default_rng(seed)
    polys = list(building.iter_polygons())
    walls = [p for p in polys if p.surface_class == "WallSurface"][:TEXTURED]
    tiles = (
        TextureTile(f"textures/{building.id}_0.png", rng.integers(0, 65535, (48, 32), dtype=np.uint16)),
        TextureTile(f"textures/{building.id}_1.png", rng.integers(1, 65535, (16, 24), dtype=np.uint16)),
    )

    def target(p) -> TextureTarget:
        coords = {}
        for r in p.rings:
            st = rng.uniform(0.0, 1.0, (len(r.coords), 2))
            st[-1] = st[0]
            coords[r.id] = st
        return TextureTarget(polygon_id=p.id, ring_coords=coords)

    app = Appearance(
        theme=theme,
        surface_data=(
            ParameterizedTexture(
                id=f"tex_{seed}_0", image_uri=tiles[0].name, targets=tuple(map(target, walls[:4]))
            ),
            ParameterizedTexture(
                id=f"tex_{seed}_1", image_uri=tiles[1].name, targets=tuple(map(target, walls[4:]))
            ),
        ),
        id=f"app_{seed}",
    )
    textured = {p.id for p in walls}
    stats = []
    for k, p in enumerate(polys):
        obs = 100 + k if p.id in textured else 0
        temp = (
            {
                "mean": 270.0 + k,
                "median": 269.5 + k,
                "std": 1.5,
                "min": 260.0,
                "max": 290.0 + k,
                "p05": 262.0,
                "p25": 266.0,
                "p75": 274.0,
                "p95": 280.0 + k,
            }
            if obs
            else {}
        )
        figures = (
            {"typical": 269.0 + k, "spread": 0.4, "hot_share": 0.02, "window_share": 0.1,
             "heat_loss_index": 0.03, "windows": 2, "leaks": 1}
            if obs
            else {}
        )  # fmt: skip
        stats.append(
            SurfaceStats(
                p.id, building.id, p.surface_class, 200, obs, (0, 1) if obs else (), 0.05, 30.0, temp,
                **figures,
            )
        )  # fmt: skip
    c0 = building.bounds()[0] - np.array([20.0, 20.0, -2.0])
    poses = tuple(
        FramePose(i, building.id, Pose(np.eye(3), c0 + i), "refined" if i else "prior", 0.4 + i, 20 + i)
        for i in range(2)
    )
    w = walls[0].exterior.coords
    outline = np.vstack([w[:3], w[:1]])
    anomaly = Anomaly(
        building.id, walls[0].id, outline, outline[:3].mean(axis=0), 1.5, 4.0, 2.5,
        id=f"{walls[0].id}-leak-0", frames=3, best_resolution_m=0.04, confidence=0.8,
    )  # fmt: skip
    return BuildingResult(
        building.id, app, tiles, radiometry, tuple(stats), poses, (anomaly,), {"texture": 1.0, "orient": 2.0}
    )


@pytest.fixture(scope="module")
def model(db_engine):
    """The Bavarian sample imported once: (engine, model id, header, building)."""
    header, buildings = read_model(SAMPLE)
    s = import_citygml(db_engine, SAMPLE, name="store-export-bavaria")
    return db_engine, s.model_id, header, buildings[0]


def _new_job(engine, model_id: int, theme: str) -> uuid.UUID:
    with Session(engine) as session:
        jid = create_job(session, model_id=model_id, theme=theme)
        session.commit()
    return jid


def _counts(engine, job_id) -> dict[str, int]:
    q = {
        "appearance": "SELECT count(*) FROM appearance WHERE job_id = :j",
        "surface_data": "SELECT count(*) FROM surface_data sd JOIN appearance a ON a.id = sd.appearance_id "
        "WHERE a.job_id = :j",
        "texture_param": "SELECT count(*) FROM texture_param tp JOIN surface_data sd "
        "ON sd.id = tp.surface_data_id JOIN appearance a ON a.id = sd.appearance_id WHERE a.job_id = :j",
        "tex_image": "SELECT count(*) FROM tex_image ti JOIN appearance a ON a.id = ti.appearance_id "
        "WHERE a.job_id = :j",
        "surface_thermal": "SELECT count(*) FROM surface_thermal st JOIN appearance a "
        "ON a.id = st.appearance_id "
        "WHERE a.job_id = :j",
        "frame_pose": "SELECT count(*) FROM frame_pose WHERE job_id = :j",
        "thermal_anomaly": "SELECT count(*) FROM thermal_anomaly WHERE job_id = :j",
    }
    with engine.connect() as c:
        return {k: c.execute(text(sql), {"j": job_id}).scalar_one() for k, sql in q.items()}


def _member_c14n(path: Path) -> list[bytes]:
    """Canonical XML of every cityObjectMember (CityModel envelope and name left out)."""
    tree = etree.parse(str(path), etree.XMLParser(resolve_entities=False, no_network=True))
    members = tree.getroot().findall("{http://www.opengis.net/citygml/2.0}cityObjectMember")
    return [etree.tostring(m, method="c14n") for m in members]


def test_export_equals_in_process_results(model, tmp_path) -> None:
    engine, model_id, header, building = model
    result = make_result(building, "thermal-ir", seed=1, radiometry=Radiometry())
    job = _new_job(engine, model_id, "thermal-ir")
    with Session(engine) as session:
        stored = store_building_result(session, job_id=job, model_id=model_id, result=result)
    assert (stored.images, stored.textured_surfaces, stored.surfaces) == (2, TEXTURED, len(result.surfaces))
    # in-process reference: the results folder writer with the same in-memory data
    ref = tmp_path / "ref"
    ref.mkdir()
    write_textured_gml(
        ref / "textured.gml", [building], {building.id: result}, header.srs_name, display=False
    )
    for t in result.tiles:
        write_tile(ref, t)
    out = export_citygml(engine, tmp_path / "db", model=model_id, theme="thermal-ir")
    assert out.buildings == 1 and out.textures == 2
    assert validate_citygml2(out.path) == []
    assert validate_citygml2(ref / "textured.gml") == []
    # the building members are the same XML, byte for byte after canonicalisation
    assert _member_c14n(out.path) == _member_c14n(ref / "textured.gml")
    # and the same data read back: ids, coordinates, texture coordinates
    _, (got,) = read_model(out.path)
    _, (exp,) = read_model(ref / "textured.gml")
    assert [p.id for p in got.iter_polygons()] == [p.id for p in building.iter_polygons()]
    for pg, pe in zip(got.iter_polygons(), exp.iter_polygons(), strict=True):
        assert [r.id for r in pg.rings] == [r.id for r in pe.rings]
        for rg, re_ in zip(pg.rings, pe.rings, strict=True):
            np.testing.assert_array_equal(rg.coords, re_.coords)
    (app,) = got.appearances
    assert app.theme == "thermal-ir"
    for sd_got, sd_in in zip(app.surface_data, result.appearance.surface_data, strict=True):
        assert (sd_got.id, sd_got.image_uri) == (sd_in.id, sd_in.image_uri)
        for tg, ti in zip(sd_got.targets, sd_in.targets, strict=True):
            assert tg.polygon_id == ti.polygon_id and list(tg.ring_coords) == list(ti.ring_coords)
            for rid, st in ti.ring_coords.items():
                np.testing.assert_allclose(tg.ring_coords[rid], st, rtol=0, atol=1e-12)
    # anomalies.geojson in the results format
    doc = json.loads((tmp_path / "db" / "anomalies.geojson").read_text())
    assert out.anomalies == 1 and doc["crs"]["properties"]["srsName"] == header.srs_name
    assert doc["crs"]["properties"]["name"].startswith("urn:ogc:def:crs")  # as GDAL resolves it
    (feat,) = doc["features"]
    (an,) = result.anomalies
    assert feat["properties"]["building"] == building.id and feat["properties"]["surface"] == an.polygon_id
    np.testing.assert_array_equal(np.array(feat["geometry"]["coordinates"][0]), an.outline)
    assert feat["properties"]["peak_delta_k"] == an.peak_delta_k
    assert (feat["properties"]["id"], feat["properties"]["frames"], feat["properties"]["confidence"]) == (
        an.id, an.frames, an.confidence
    )  # fmt: skip
    for t in result.tiles:
        data = (tmp_path / "db" / t.name).read_bytes()
        assert data == (ref / t.name).read_bytes() == cv2.imencode(".png", t.dn)[1].tobytes()
        np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED), t.dn)


def test_store_is_idempotent_and_atomic(model, monkeypatch) -> None:
    engine, model_id, _, building = model
    job = _new_job(engine, model_id, "thermal-ir")
    with engine.begin() as c:
        c.execute(
            text(
                "INSERT INTO job_unit (job_id, building_id, status, progress, attempts, timings_s) "
                "SELECT :j, id, 'running', 0.5, 1, '{}' FROM building "
                "WHERE city_model_id = :m AND gml_id = :g"
            ),
            {"j": job, "m": model_id, "g": building.id},
        )
    first = make_result(building, "thermal-ir", seed=2, radiometry=Radiometry())
    with Session(engine) as session:
        store_building_result(session, job_id=job, model_id=model_id, result=first)
    once = _counts(engine, job)
    assert once == {
        "appearance": 1,
        "surface_data": 2,
        "texture_param": TEXTURED,
        "tex_image": 2,
        "surface_thermal": len(first.surfaces),
        "frame_pose": 2,
        "thermal_anomaly": 1,
    }
    with Session(engine) as session:
        store_building_result(session, job_id=str(job), model_id=model_id, result=first)
    assert _counts(engine, job) == once
    with engine.connect() as c:
        unit = c.execute(
            text("SELECT status, progress, timings_s FROM job_unit WHERE job_id = :j"), {"j": job}
        ).one()
        shas = set(
            c.execute(
                text(
                    "SELECT sha256 FROM tex_image ti JOIN appearance a ON a.id = ti.appearance_id "
                    "WHERE a.job_id = :j"
                ),
                {"j": job},
            ).scalars()
        )
    assert unit == ("successful", 1.0, {"texture": 1.0, "orient": 2.0})

    # a failure half way through the second write: nothing partial, the first copy stays
    second = make_result(building, "thermal-ir", seed=3, radiometry=Radiometry())
    real_copy = store_mod.copy_rows

    def failing_copy(conn, table, columns, rows):
        if table == "surface_thermal":
            raise RuntimeError("worker killed (simulated)")
        real_copy(conn, table, columns, rows)

    monkeypatch.setattr(store_mod, "copy_rows", failing_copy)
    with Session(engine) as session, pytest.raises(RuntimeError, match="simulated"):
        store_building_result(session, job_id=job, model_id=model_id, result=second)
    job2 = _new_job(engine, model_id, "thermal-ir")
    with Session(engine) as session, pytest.raises(RuntimeError, match="simulated"):
        store_building_result(session, job_id=job2, model_id=model_id, result=second)
    monkeypatch.setattr(store_mod, "copy_rows", real_copy)
    assert _counts(engine, job) == once
    assert set(_counts(engine, job2).values()) == {0}
    with engine.connect() as c:
        after = set(
            c.execute(
                text(
                    "SELECT sha256 FROM tex_image ti JOIN appearance a ON a.id = ti.appearance_id "
                    "WHERE a.job_id = :j"
                ),
                {"j": job},
            ).scalars()
        )
    assert after == shas

    # dangling references are refused before anything is written
    bad = BuildingResult(building.id, second.appearance, second.tiles[:1], Radiometry(), second.surfaces)
    with Session(engine) as session, pytest.raises(InputDataError, match="not among the tiles"):
        store_building_result(session, job_id=job2, model_id=model_id, result=bad)
    assert set(_counts(engine, job2).values()) == {0}


def test_two_themes_stay_apart(model, tmp_path) -> None:
    engine, model_id, _, building = model
    r1 = make_result(building, "tir-2024-winter", seed=4, radiometry=Radiometry(unit="K", scale=0.01))
    r2 = make_result(
        building, "tir-2025-winter", seed=5, radiometry=Radiometry(unit="degC", scale=0.01, offset=-50)
    )
    j1, j2 = _new_job(engine, model_id, r1.appearance.theme), _new_job(engine, model_id, r2.appearance.theme)
    with Session(engine) as session:
        store_building_result(session, job_id=j1, model_id=model_id, result=r1, commit=False)
        store_building_result(session, job_id=j2, model_id=model_id, result=r2, commit=False)
        session.commit()
    sha = {
        r.appearance.theme: {
            hashlib.sha256(cv2.imencode(".png", t.dn)[1].tobytes()).hexdigest() for t in r.tiles
        }
        for r in (r1, r2)
    }
    with engine.connect() as c:
        for theme in sha:
            got = set(
                c.execute(
                    text(
                        "SELECT ti.sha256 FROM texture_param tp "
                        "JOIN surface_data sd ON sd.id = tp.surface_data_id "
                        "JOIN appearance a ON a.id = sd.appearance_id "
                        "JOIN tex_image ti ON ti.id = sd.tex_image_id "
                        "WHERE a.theme = :t AND a.city_model_id = :m"
                    ),
                    {"t": theme, "m": model_id},
                ).scalars()
            )
            assert got == sha[theme]
        # GIS views: one facade row per textured surface and theme, kelvin, model SRID
        rows = c.execute(
            text(
                "SELECT theme, surface_gml_id, mean_k, ST_SRID(geometry), observed_share FROM facade_thermal "
                "WHERE model_name = 'store-export-bavaria' AND theme LIKE 'tir-20%' "
                "ORDER BY theme, surface_gml_id"
            ),
        ).all()
        bt = c.execute(
            text(
                "SELECT theme, surfaces, observed_surfaces, ST_SRID(footprint), max_k FROM building_thermal "
                "WHERE model_name = 'store-export-bavaria' AND theme LIKE 'tir-20%' ORDER BY theme"
            ),
        ).all()
    assert len(rows) == 2 * TEXTURED
    stats1 = {s.polygon_id: s for s in r1.surfaces}
    for theme, pid, mean_k, srid, share in rows:
        expected = stats1[pid].temperature["mean"] + (273.15 if theme == "tir-2025-winter" else 0.0)
        assert mean_k == pytest.approx(expected, abs=1e-9)
        assert srid == TEST_SRID and share == pytest.approx(stats1[pid].observed_share)
    assert [(t, n, o, s) for t, n, o, s, _ in bt] == [
        ("tir-2024-winter", len(r1.surfaces), TEXTURED, TEST_SRID),
        ("tir-2025-winter", len(r1.surfaces), TEXTURED, TEST_SRID),
    ]
    # export per theme: only that theme's appearance and texture coordinates
    for r in (r1, r2):
        out = export_citygml(
            engine, tmp_path / r.appearance.theme, model="store-export-bavaria", theme=r.appearance.theme
        )
        assert validate_citygml2(out.path) == []
        _, (b,) = read_model(out.path)
        (app,) = b.appearances
        assert app.theme == r.appearance.theme
        for sd_got, sd_in in zip(app.surface_data, r.appearance.surface_data, strict=True):
            for tg, ti in zip(sd_got.targets, sd_in.targets, strict=True):
                for rid, st in ti.ring_coords.items():
                    np.testing.assert_allclose(tg.ring_coords[rid], st, rtol=0, atol=1e-12)
        for t in r.tiles:
            assert cv2.imencode(".png", t.dn)[1].tobytes() == (out.path.parent / t.name).read_bytes()
    # export of every theme: both appearances; equal tile names get distinct files with the right bytes
    out = export_citygml(engine, tmp_path / "all", model="store-export-bavaria", job_id=None)
    assert validate_citygml2(out.path) == []
    _, (b,) = read_model(out.path)
    by_theme = {a.theme: a for a in b.appearances}
    assert {"tir-2024-winter", "tir-2025-winter"} <= set(by_theme)
    for r in (r1, r2):
        app = by_theme[r.appearance.theme]
        for sd_got, tile in zip(app.surface_data, r.tiles, strict=True):
            data = (out.path.parent / sd_got.image_uri).read_bytes()
            assert data == cv2.imencode(".png", tile.dn)[1].tobytes()


def test_untextured_building_result(model, tmp_path) -> None:
    """A unit that observed nothing: statistics and poses are stored, the export of its theme is
    empty and no facade row appears."""
    engine, model_id, _, building = model
    full = make_result(building, "tir-empty", seed=6, radiometry=Radiometry())
    stats = tuple(
        SurfaceStats(s.polygon_id, s.building_id, s.surface_class, s.texels_total, 0) for s in full.surfaces
    )
    empty = BuildingResult(building.id, None, (), Radiometry(), stats, full.poses)
    job = _new_job(engine, model_id, "tir-empty")
    with Session(engine) as session:
        stored = store_building_result(session, job_id=job, model_id=model_id, result=empty)
    assert (stored.images, stored.textured_surfaces, stored.surfaces, stored.poses) == (0, 0, len(stats), 2)
    out = export_citygml(engine, tmp_path, model=model_id, theme="tir-empty")
    assert out.buildings == 0 and validate_citygml2(out.path) == []
    with engine.connect() as c:
        n = c.execute(text("SELECT count(*) FROM facade_thermal WHERE theme = 'tir-empty'")).scalar_one()
        share = c.execute(
            text("SELECT observed_share FROM building_thermal WHERE theme = 'tir-empty'")
        ).scalar_one()
    assert n == 0 and share == 0.0


def test_concurrent_duplicate_deliveries_leave_one_copy(model) -> None:
    """The same unit result delivered twice at once (two workers): exactly one copy remains."""
    import threading

    engine, model_id, _, building = model
    job = _new_job(engine, model_id, "thermal-ir")
    result = make_result(building, "thermal-ir", seed=8, radiometry=Radiometry())
    errors: list[BaseException] = []
    barrier = threading.Barrier(3)

    def deliver() -> None:
        try:
            with Session(engine) as session:
                barrier.wait(timeout=10)
                store_building_result(session, job_id=job, model_id=model_id, result=result)
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=deliver) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert errors == []
    assert _counts(engine, job) == {
        "appearance": 1,
        "surface_data": 2,
        "texture_param": TEXTURED,
        "tex_image": 2,
        "surface_thermal": len(result.surfaces),
        "frame_pose": 2,
        "thermal_anomaly": 1,
    }


def test_stored_result_reads_back(model) -> None:
    """store -> load gives the same BuildingResult (the service writes report/orientation from it)."""
    from db.jobs import add_units
    from db.result_load import load_building_result

    engine, model_id, _, building = model
    job = _new_job(engine, model_id, "thermal-ir")
    with Session(engine) as session:
        add_units(session, job_id=job, building_gml_ids=[building.id])
        session.commit()
    r = make_result(
        building, "thermal-ir", seed=10, radiometry=Radiometry(unit="degC", scale=0.02, offset=-40.0)
    )
    with Session(engine) as session:
        store_building_result(session, job_id=job, model_id=model_id, result=r)
        back = load_building_result(session, job_id=job, model_id=model_id, building_gml_id=building.id)
    assert back.building_id == r.building_id and back.timings_s == dict(r.timings_s)
    assert (back.radiometry.unit, back.radiometry.scale, back.radiometry.offset) == ("degC", 0.02, -40.0)
    assert back.appearance.theme == r.appearance.theme and back.appearance.id == r.appearance.id
    for sd_b, sd_r in zip(back.appearance.surface_data, r.appearance.surface_data, strict=True):
        assert (sd_b.id, sd_b.image_uri) == (sd_r.id, sd_r.image_uri)
        for tb, tr in zip(sd_b.targets, sd_r.targets, strict=True):
            assert tb.polygon_id == tr.polygon_id and list(tb.ring_coords) == list(tr.ring_coords)
            for rid in tr.ring_coords:
                np.testing.assert_array_equal(tb.ring_coords[rid], tr.ring_coords[rid])
    assert [t.name for t in back.tiles] == [t.name for t in r.tiles]
    for tb, tr in zip(back.tiles, r.tiles, strict=True):
        assert tb.dn.dtype == np.uint16
        np.testing.assert_array_equal(tb.dn, tr.dn)
    assert len(back.surfaces) == len(r.surfaces)
    for sb, sr in zip(back.surfaces, r.surfaces, strict=True):
        assert (sb.polygon_id, sb.building_id, sb.surface_class) == (
            sr.polygon_id,
            sr.building_id,
            sr.surface_class,
        )
        assert (sb.texels_total, sb.texels_observed, sb.frames_used) == (
            sr.texels_total,
            sr.texels_observed,
            sr.frames_used,
        )
        assert sb.mean_resolution_m == sr.mean_resolution_m and dict(sb.temperature) == dict(sr.temperature)
        figures = ("typical", "spread", "hot_share", "window_share", "heat_loss_index", "windows", "leaks")
        np.testing.assert_equal([getattr(sb, f) for f in figures], [getattr(sr, f) for f in figures])
    for pb, pr in zip(back.poses, r.poses, strict=True):
        assert (pb.frame, pb.status, pb.matches, pb.rms_px) == (pr.frame, pr.status, pr.matches, pr.rms_px)
        np.testing.assert_array_equal(pb.pose.center, pr.pose.center)
        np.testing.assert_array_equal(pb.pose.R_world_from_cam, pr.pose.R_world_from_cam)
    (ab,), (ar,) = back.anomalies, r.anomalies
    np.testing.assert_array_equal(ab.outline, ar.outline)
    assert (ab.polygon_id, ab.area_m2, ab.peak_delta_k, ab.kind) == (
        ar.polygon_id,
        ar.area_m2,
        ar.peak_delta_k,
        ar.kind,
    )
    assert (ab.id, ab.frames, ab.best_resolution_m, ab.confidence) == (
        ar.id, ar.frames, ar.best_resolution_m, ar.confidence
    )  # fmt: skip
