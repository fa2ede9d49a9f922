"""OGC API - Features of the HTTP API (`docs/features.md`), served by `citytherm serve` over HTTP
against the real PostGIS test database, read by clients no one here wrote: GDAL's OAPIF driver
(`ogrinfo`, `ogr2ogr`; Debian's GDAL 3.6) and a plain HTTP client following `next` links.

Data: the Bavarian sample with one stored job result (`db.store`: textures, statistics, an
anomaly), and the NRW tile (2,000+ surfaces) with the thermal rows of eight jobs replicated in SQL
(> 10,000 facades, an anomaly per building), the facade feature texts of half of them written as
`db.store` writes them, one job's texts stale (another definition's) and the others without: a
page mixes texts read and features the service writes."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
import uuid

import httpx
import pytest
from pyproj import Transformer
from sqlalchemy import text
from sqlalchemy.orm import Session

from db.citygml.reader import read_model
from db.facade_features import stored_properties, write_feature_texts
from db.importer import import_citygml
from db.store import create_job, store_building_result
from services.api import features_sql
from services.api.features_collections import COLLECTIONS
from services.api.features_params import parse_crs
from tests.conftest import DATA
from tests.integration.conftest import TEST_SRID, ApiServer, assert_problem, citytherm_exe, new_api_key
from tests.integration.test_db_store_export import make_result
from workers.pipeline.geometry.manifest import Radiometry

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(shutil.which("ogrinfo") is None, reason="GDAL (gdal-bin) is not installed"),
]

CRS84 = "http://www.opengis.net/def/crs/OGC/1.3/CRS84"
DB_CRS = f"http://www.opengis.net/def/crs/EPSG/0/{TEST_SRID}"
NRW_JOBS = 8
FACADES_SQL = (
    "FROM surface_thermal st JOIN surface s ON s.id = st.surface_id "
    "JOIN city_model cm ON cm.id = s.city_model_id AND cm.state = 'complete'"
)


@pytest.fixture(scope="module")
def data(db_engine) -> dict:
    """Both models with their results: names, ids, jobs."""
    tag = uuid.uuid4().hex[:6]
    bav_path = DATA / "bavaria-1-building-citygml2-lod2.gml"
    _, (building,) = read_model(bav_path)
    bav = import_citygml(db_engine, bav_path, name=f"feat-bav-{tag}").model_id
    nrw = import_citygml(db_engine, DATA / "nrw-tile-5659-citygml1-lod2.gml", name=f"feat-nrw-{tag}").model_id
    with Session(db_engine) as s:
        bav_job = create_job(s, model_id=bav, theme="tir-bav")
        jobs = [create_job(s, model_id=nrw, theme=f"tir-{k % 2}") for k in range(NRW_JOBS)]
        s.commit()
        store_building_result(
            s, job_id=bav_job, model_id=bav, result=make_result(building, "tir-bav", 3, Radiometry())
        )
    with db_engine.begin() as c:
        for k, job in enumerate(jobs):  # one appearance per building, statistics for every surface
            c.execute(
                text(
                    "INSERT INTO appearance (city_model_id, building_id, job_id, theme, ordinal) "
                    "SELECT b.city_model_id, b.id, j.id, j.theme, 0 FROM building b JOIN job j ON j.id = :j "
                    "WHERE b.city_model_id = :m AND b.parent_id IS NULL"
                ),
                {"j": job, "m": nrw},
            )
            c.execute(
                text(
                    "INSERT INTO surface_thermal (appearance_id, surface_id, texels_total, "
                    "texels_observed, observed_share, frames_used, resolution_m, mean_k, min_k, max_k, "
                    "p95_k, temperature, unit) SELECT a.id, s.id, 100, 80, 0.8, ARRAY[1, 2], 0.05, "
                    "270 + (s.id % 20) + :k, 260, 300, 290, '{}'::jsonb, 'kelvin' FROM appearance a "
                    "JOIN building p ON p.root_id = a.building_id "
                    "JOIN surface s ON s.building_id = p.id WHERE a.job_id = :j"
                ),
                {"j": job, "k": k},
            )
            if k % 2 == 0:  # their feature texts, as `db.store` writes them; none for the odd jobs
                of_job = "st.appearance_id IN (SELECT id FROM appearance WHERE job_id = :j)"
                write_feature_texts(c, of_job, {"j": job})
        c.execute(  # one job's texts as another definition of the features would have left them
            text(
                "UPDATE surface_thermal st SET feature = 'stale', feature_spec = 1 FROM appearance a "
                "WHERE a.id = st.appearance_id AND a.job_id = :j"
            ),
            {"j": jobs[2]},
        )
        c.execute(  # an anomaly on the first wall of every building, for the first job
            text(
                "INSERT INTO thermal_anomaly (job_id, appearance_id, building_id, surface_id, kind, outline, "
                "centre, area_m2, peak_delta_k, mean_delta_k) "
                "SELECT DISTINCT ON (a.building_id) a.job_id, a.id, s.building_id, s.id, "
                "CASE WHEN s.id % 3 = 0 THEN 'window' ELSE 'leak' END, s.geometry, ARRAY[0, 0, 0], "
                "1.5, 4.0, 2.5 FROM appearance a JOIN building p ON p.root_id = a.building_id "
                "JOIN surface s ON s.building_id = p.id WHERE a.job_id = :j "
                "AND s.surface_class = 'WallSurface' AND s.geometry IS NOT NULL ORDER BY a.building_id, s.id"
            ),
            {"j": jobs[0]},
        )
    return {"bav": bav, "nrw": nrw, "bav_job": str(bav_job), "jobs": [str(j) for j in jobs]}


@pytest.fixture(scope="module")
def server(api_server_factory, data) -> ApiServer:
    """The API (reads need a key)."""
    return api_server_factory()


@pytest.fixture(scope="module")
def gdal_env(server: ApiServer, tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Environment for GDAL's utilities: the read key as a header (GDAL_HTTP_HEADER_FILE)."""
    header = tmp_path_factory.mktemp("gdal") / "headers.txt"
    header.write_text(f"Authorization: Bearer {server.keys['read']}\n")
    return {**os.environ, "GDAL_HTTP_HEADER_FILE": str(header), "CPL_VSIL_CURL_CACHE_SIZE": "0"}


def _gdal(env: dict[str, str], *args: str) -> str:
    out = subprocess.run(list(args), env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr + out.stdout
    return out.stdout


def _ids(engine, sql: str, **params: object) -> list[int]:
    with engine.connect() as c:
        return [int(r[0]) for r in c.execute(text(sql), params)]


# -- documents and GDAL ------------------------------------------------------------------------
def test_landing_conformance_collections(server: ApiServer, data) -> None:
    with server.client("read") as c:
        links = {link["rel"]: link["href"] for link in c.get("/").json()["links"]}
        assert links["data"].endswith("/collections") and links["service-desc"].endswith("/openapi.json")
        conf = c.get("/conformance").json()["conformsTo"]
        assert "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/core" in conf
        assert "http://www.opengis.net/spec/ogcapi-features-2/1.0/conf/crs" in conf
        assert "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/core" in conf
        colls = {col["id"]: col for col in c.get("/collections").json()["collections"]}
        assert set(colls) == {"buildings", "facades", "anomalies", "jobs"}
        fac = c.get("/collections/facades").json()
        assert fac["storageCrs"] == DB_CRS and CRS84 in fac["crs"] and DB_CRS in fac["crs"]
        lon0, lat0, lon1, lat1 = fac["extent"]["spatial"]["bbox"][0]
        assert 5 < lon0 < lon1 < 16 and 47 < lat0 < lat1 < 56  # Germany
        assert len(fac["extent"]["spatial"]["storageCrsBbox"][0]) == 6
        assert_problem(c.get("/collections/nothing"), 404)
        assert_problem(c.get("/collections/facades/items/999999999999"), 404)
        assert_problem(c.get("/collections/facades/items/abc"), 404)
        assert_problem(c.get("/collections/jobs/items/" + str(uuid.uuid4())), 404)
    with server.client(None) as c:
        assert_problem(c.get("/collections/facades/items"), 401)


def test_gdal_lists_collections_3d_and_crs(server: ApiServer, gdal_env) -> None:
    out = _gdal(gdal_env, "ogrinfo", "-ro", "-so", f"OAPIF:{server.base}")
    for name in ("buildings", "facades", "anomalies", "jobs"):
        assert f": {name}" in out, out
    info = _gdal(gdal_env, "ogrinfo", "-ro", "-so", f"OAPIF:{server.base}", "facades")
    assert "Geometry: 3D Polygon" in info, info
    # GDAL 3.6's OAPIF driver predates Part 2 (CRS): it reads the default output, CRS84, as WGS 84
    assert 'ID["EPSG",4326]' in info
    b_info = _gdal(gdal_env, "ogrinfo", "-ro", "-so", f"OAPIF:{server.base}", "buildings")
    assert "Geometry: 3D Multi Polygon" in b_info, b_info
    # in the database CRS by reference (Part 2): GDAL's GeoJSON reader sees EPSG:<database SRID>
    url = f"{server.base}/collections/facades/items?limit=5&crs={DB_CRS}"
    g_info = _gdal(gdal_env, "ogrinfo", "-ro", "-so", "-al", f"GeoJSON:{url}")
    assert f'ID["EPSG",{TEST_SRID}]' in g_info and "3D Polygon" in g_info, g_info


@pytest.mark.parametrize("collection", ["facades", "buildings", "anomalies", "jobs"])
def test_gdal_reads_every_row(server: ApiServer, gdal_env, db_engine, data, collection, tmp_path) -> None:
    sql = {
        "facades": f"SELECT st.id {FACADES_SQL} ORDER BY 1",
        "buildings": "SELECT b.id FROM building b JOIN city_model cm ON cm.id = b.city_model_id "
        "AND cm.state = 'complete' WHERE b.parent_id IS NULL ORDER BY 1",
        "anomalies": "SELECT ta.id FROM thermal_anomaly ta JOIN building b ON b.id = ta.building_id "
        "JOIN city_model cm ON cm.id = b.city_model_id AND cm.state = 'complete' ORDER BY 1",
        "jobs": "SELECT j.id FROM job j JOIN city_model cm ON cm.id = j.city_model_id "
        "AND cm.state = 'complete' ORDER BY 1",
    }[collection]
    with db_engine.connect() as c:
        want = sorted(str(r[0]) for r in c.execute(text(sql)))
    out = tmp_path / f"{collection}.geojson"
    src = f"OAPIF:{server.base}"
    opts = ("-f", "GeoJSON", "-preserve_fid", "-oo", "PAGE_SIZE=2000")
    _gdal(gdal_env, "ogr2ogr", *opts, str(out), src, collection)
    feats = json.loads(out.read_text())["features"]
    got = sorted(str(f["properties"].get("id", f.get("id"))) for f in feats)
    assert len(feats) == len(want) and got == want
    if collection == "facades":
        assert len(want) > 10_000 and all(len(f["geometry"]["coordinates"][0][0]) == 3 for f in feats[:50])


# -- paging ------------------------------------------------------------------------------------
def test_paging_returns_each_facade_once(server: ApiServer, db_engine, data) -> None:
    want = _ids(db_engine, f"SELECT st.id {FACADES_SQL} ORDER BY 1")
    assert len(want) >= 10_000
    seen: list[int] = []
    pages = 0
    with server.client("read") as c:
        r = c.get("/collections/facades/items", params={"limit": 250})
        while True:
            assert r.status_code == 200 and r.headers["content-type"].startswith("application/geo+json")
            doc = r.json()
            assert doc["numberMatched"] == len(want) and doc["numberReturned"] == len(doc["features"])
            seen += [f["id"] for f in doc["features"]]
            pages += 1
            nxt = [link["href"] for link in doc["links"] if link["rel"] == "next"]
            if not nxt:
                break
            r = c.get(nxt[0])
        assert seen == want and pages == -(-len(want) // 250)
        # back from the last page: prev links lead to the same features
        prev = next(link["href"] for link in doc["links"] if link["rel"] == "prev")
        back = c.get(prev).json()
        last = len(doc["features"])
        assert [f["id"] for f in back["features"]] == want[-250 - last : -last]
        # limit: default 100, clamped to 10,000
        assert c.get("/collections/facades/items").json()["numberReturned"] == 100
        big = c.get("/collections/facades/items", params={"limit": 50_000}).json()
        assert big["numberReturned"] == 10_000
        assert "limit=10000" in next(link["href"] for link in big["links"] if link["rel"] == "next")


def test_stored_feature_texts_are_what_the_service_writes(server: ApiServer, db_engine, data) -> None:
    """The facade texts kept with the rows (`db.store` wrote the Bavarian job's, the fixture half
    the NRW jobs') are byte for byte the features the service writes in CRS84, with the spec of
    its definition; a page serves them and writes the others (stale spec, none) the same way."""
    fac, props = COLLECTIONS["facades"], stored_properties()
    crs84 = parse_crs(None, TEST_SRID)
    spec = features_sql.stored_spec(fac, props)
    with db_engine.connect() as conn:
        texts = text("SELECT id, feature FROM surface_thermal WHERE feature_spec = :s")
        stored = dict(conn.execute(texts, {"s": spec}).all())
        sql = text(features_sql.features_by_key_sql(fac, props, crs84))
        written = dict(conn.execute(sql, {"keys": sorted(stored), "srid": TEST_SRID}).all())
        others = conn.execute(
            text("SELECT count(*) FROM surface_thermal WHERE feature_spec IS DISTINCT FROM :s"), {"s": spec}
        ).scalar_one()
    of_bav = "JOIN appearance a ON a.id = st.appearance_id WHERE a.job_id = :j"
    bav = _ids(db_engine, f"SELECT st.id {FACADES_SQL} {of_bav}", j=data["bav_job"])
    assert bav and set(bav) <= set(stored) and len(stored) > 1000 and others > 1000
    assert stored == written
    with server.client("read") as c:
        page = c.get("/collections/facades/items", params={"limit": 2000}).json()["features"]
    kinds = {k in stored for k in (f["id"] for f in page)}
    assert kinds == {True, False}
    assert all(f == json.loads(stored[f["id"]]) for f in page if f["id"] in stored)


def test_paging_backwards_and_by_uuid(server: ApiServer, db_engine, data) -> None:
    """`prev` links from the last page back to the first return every facade once (pages in
    reverse order, each ascending), and the first page reached backwards has no `prev`; the
    jobs collection (UUID keys) pages one feature at a time forward and back in key order."""
    want = _ids(db_engine, f"SELECT st.id {FACADES_SQL} ORDER BY 1")
    with server.client("read") as c:
        doc = c.get("/collections/facades/items", params={"limit": 1000}).json()
        while nxt := [link["href"] for link in doc["links"] if link["rel"] == "next"]:
            doc = c.get(nxt[0]).json()
        pages = [[f["id"] for f in doc["features"]]]
        while prev := [link["href"] for link in doc["links"] if link["rel"] == "prev"]:
            doc = c.get(prev[0]).json()
            assert doc["numberReturned"] == len(doc["features"]) == 1000
            assert doc["numberMatched"] == len(want)
            assert any(link["rel"] == "next" for link in doc["links"])
            pages.append([f["id"] for f in doc["features"]])
        assert [i for page in reversed(pages) for i in page] == want
        assert pages[-1] == want[:1000] and len(pages) == -(-len(want) // 1000)
        # jobs: UUID keys, one per page
        with db_engine.connect() as conn:
            jobs = [
                str(r[0])
                for r in conn.execute(
                    text("SELECT j.id FROM job j JOIN city_model cm ON cm.id = j.city_model_id "
                         "AND cm.state = 'complete' ORDER BY j.id")
                )
            ]  # fmt: skip
        assert len(jobs) >= NRW_JOBS + 1
        doc = c.get("/collections/jobs/items", params={"limit": 1}).json()
        forward = [doc["features"][0]["id"]]
        while nxt := [link["href"] for link in doc["links"] if link["rel"] == "next"]:
            doc = c.get(nxt[0]).json()
            assert doc["numberReturned"] == 1 and doc["numberMatched"] == len(jobs)
            forward.append(doc["features"][0]["id"])
        backward = [doc["features"][0]["id"]]
        while prev := [link["href"] for link in doc["links"] if link["rel"] == "prev"]:
            doc = c.get(prev[0]).json()
            backward.append(doc["features"][0]["id"])
        assert forward == jobs and backward == jobs[::-1]
        # RFC 7946 geometries (no crs member of their own); the storage CRS named once, at the top
        for crs, legacy in ((None, None), (DB_CRS, f"urn:ogc:def:crs:EPSG::{TEST_SRID}")):
            page = c.get("/collections/facades/items", params={"limit": 5, **({"crs": crs} if crs else {})})
            body = page.json()
            geometries = [f["geometry"] for f in body["features"]]
            assert len(geometries) == 5 and all("crs" not in g and g["type"] == "Polygon" for g in geometries)
            assert body.get("crs", {}).get("properties", {}).get("name") == legacy


def test_bbox_and_crs(server: ApiServer, db_engine, data) -> None:
    with db_engine.connect() as c:
        x0, y0, x1, y1 = c.execute(
            text("SELECT ST_XMin(e), ST_YMin(e), ST_XMax(e), ST_YMax(e) FROM (SELECT ST_Extent(envelope) e "
                 "FROM building WHERE city_model_id = :m) x"),
            {"m": data["nrw"]},
        ).one()  # fmt: skip
    w, h = x1 - x0, y1 - y0  # a box whose edges cut through the model, touching no surface
    box = (x0 + 0.137 * w, y0 + 0.211 * h, x0 + 0.613 * w, y0 + 0.587 * h)
    want = _ids(
        db_engine,
        f"SELECT st.id {FACADES_SQL} WHERE ST_Intersects(s.geometry, ST_MakeEnvelope(:a, :b, :c, :d, :s)) "
        "ORDER BY 1",
        a=box[0], b=box[1], c=box[2], d=box[3], s=TEST_SRID,
    )  # fmt: skip
    assert 0 < len(want) < 10_000
    to84 = Transformer.from_crs(f"EPSG:{TEST_SRID}", "OGC:CRS84", always_xy=True)
    with server.client("read") as c:
        q = {"bbox": ",".join(map(str, box)), "bbox-crs": DB_CRS, "limit": 10_000}
        r = c.get("/collections/facades/items", params=q)
        assert sorted(f["id"] for f in r.json()["features"]) == want
        assert r.headers["content-crs"] == f"<{CRS84}>"
        # the same box in CRS84 (its corners; the box in between is curved: PostGIS says which)
        lo, la = to84.transform([box[0], box[2]], [box[1], box[3]])
        want84 = _ids(
            db_engine,
            f"SELECT st.id {FACADES_SQL} WHERE ST_Intersects(ST_Transform(s.geometry, 4326), "
            "ST_MakeEnvelope(:a, :b, :c, :d, 4326)) ORDER BY 1",
            a=lo[0], b=la[0], c=lo[1], d=la[1],
        )  # fmt: skip
        q84 = {"bbox": f"{lo[0]},{la[0]},{lo[1]},{la[1]}", "limit": 10_000}
        got84 = c.get("/collections/facades/items", params=q84).json()["features"]
        assert sorted(f["id"] for f in got84) == want84
        # CRS84 output against pyproj, heights kept; the database CRS by reference
        fid = want[0]
        native = c.get(f"/collections/facades/items/{fid}", params={"crs": DB_CRS})
        assert native.headers["content-crs"] == f"<{DB_CRS}>"
        geo = c.get(f"/collections/facades/items/{fid}")
        assert geo.headers["content-crs"] == f"<{CRS84}>"
        x, y, z = native.json()["geometry"]["coordinates"][0][0]
        lon, lat, h = geo.json()["geometry"]["coordinates"][0][0]
        elon, elat = to84.transform(x, y)
        assert abs(lon - elon) <= 1e-7 and abs(lat - elat) <= 1e-7 and h == pytest.approx(z, abs=1e-6)
        with db_engine.connect() as conn:
            stored = conn.execute(
                text("SELECT ST_X(p), ST_Y(p), ST_Z(p) FROM (SELECT ST_PointN(ST_ExteriorRing(s.geometry), "
                     "1) p FROM surface_thermal st JOIN surface s ON s.id = st.surface_id "
                     "WHERE st.id = :i) x"),
                {"i": fid},
            ).one()  # fmt: skip
        assert (x, y, z) == pytest.approx(tuple(stored), abs=1e-6)
        items = c.get("/collections/facades/items", params={"crs": f"EPSG:{TEST_SRID}", "limit": 3})
        assert items.headers["content-crs"] == f"<{DB_CRS}>"
        assert_problem(c.get("/collections/facades/items", params={"crs": "EPSG:4326"}), 400)
        assert_problem(c.get("/collections/facades/items", params={"bbox": "1,2,3"}), 400)


def test_filters(server: ApiServer, db_engine, data) -> None:
    def count(c: httpx.Client, coll: str, **q: object) -> int:
        r = c.get(f"/collections/{coll}/items", params={**q, "limit": 1})
        assert r.status_code == 200, r.text
        return r.json()["numberMatched"]

    def db(sql: str, **p: object) -> int:
        with db_engine.connect() as conn:
            return conn.execute(text(sql), p).scalar_one()

    job = data["jobs"][1]
    with server.client("read") as c:
        of_job = db(
            "SELECT count(*) FROM appearance a JOIN surface_thermal st ON st.appearance_id = a.id "
            "WHERE a.job_id = :j",
            j=job,
        )
        assert count(c, "facades", job=job) == of_job
        walls = db(
            f"SELECT count(*) {FACADES_SQL} JOIN appearance a ON a.id = st.appearance_id "
            "WHERE a.theme = 'tir-0' AND s.surface_class = 'WallSurface' AND st.mean_k >= 285"
        )
        assert 0 < count(c, "facades", theme="tir-0", **{"class": "WallSurface"}, min_mean_k=285) == walls
        doc = c.get("/collections/facades/items", params={"theme": "tir-bav", "limit": 1000}).json()
        assert doc["features"] and {f["properties"]["job"] for f in doc["features"]} == {data["bav_job"]}
        assert any(f["properties"]["textured"] for f in doc["features"])
        bld = doc["features"][0]["properties"]["building"]
        assert count(c, "buildings", building=bld) == 1
        b = c.get("/collections/buildings/items", params={"building": bld, "theme": "tir-bav"}).json()
        props = b["features"][0]["properties"]
        assert props["theme"] == "tir-bav" and props["mean_k"] > 200 and props["measured_height_m"] > 30
        assert b["features"][0]["geometry"]["type"] == "MultiPolygon"
        assert count(c, "anomalies", kind="window") == db(
            "SELECT count(*) FROM thermal_anomaly WHERE kind = 'window'"
        )
        assert count(c, "anomalies", job=data["jobs"][0]) > 100
        with db_engine.connect() as conn:  # the detector's columns (migration 0010) once they exist
            have = set(conn.execute(text(
                "SELECT table_name || '.' || column_name FROM information_schema.columns "
                "WHERE table_name IN ('thermal_anomaly', 'surface_thermal')"
            )).scalars())  # fmt: skip
        anomaly = c.get("/collections/anomalies/items", params={"limit": 1}).json()["features"][0]
        optional = {n for n in ("anomaly_id", "frames", "confidence") if f"thermal_anomaly.{n}" in have}
        assert optional <= set(anomaly["properties"]) and anomaly["geometry"]["type"] == "Polygon"
        facade = c.get("/collections/facades/items", params={"limit": 1}).json()["features"][0]
        optional = {n for n in ("typical_k", "hot_share", "leaks") if f"surface_thermal.{n}" in have}
        assert optional <= set(facade["properties"])
        jobs = c.get("/collections/jobs/items").json()["features"]
        first = {f["id"]: f["properties"] for f in jobs}[data["jobs"][0]]
        assert first["footprint"] == "textured" and first["textured_buildings"] > 100
        with db_engine.connect() as conn:  # the NRW model's box: its jobs, not the Bavarian one's
            box = conn.execute(
                text("SELECT concat_ws(',', ST_XMin(e), ST_YMin(e), ST_XMax(e), ST_YMax(e)) FROM "
                     "(SELECT ST_Extent(footprint) e FROM building WHERE city_model_id = :m) x"),
                {"m": data["nrw"]},
            ).scalar_one()  # fmt: skip
        near = c.get("/collections/jobs/items", params={"bbox": box, "bbox-crs": DB_CRS}).json()["features"]
        assert {f["id"] for f in near} == set(data["jobs"])
        bad = assert_problem(c.get("/collections/facades/items", params={"colour": "red"}), 400)
        assert "colour" in bad["detail"]
        assert_problem(c.get("/collections/facades/items", params={"min_mean_k": "warm"}), 400)
        assert_problem(c.get("/collections/facades/items", params={"job": "not-a-uuid"}), 400)
        # `kind` filters anomalies, not facades
        assert_problem(c.get("/collections/facades/items", params={"kind": "leak"}), 400)
        assert_problem(c.get("/collections/facades/items", params={"cursor": "garbage"}), 400)
        assert_problem(c.get("/collections/facades/items", params={"limit": "0"}), 400)


# -- access ------------------------------------------------------------------------------------
def test_revoked_key_is_refused_once_the_key_cache_expires(api_server_factory, data) -> None:
    """Authenticated keys are kept `api_key_cache_s` seconds per process (`deps.KeyCache`): a
    revoked key is refused once that time has passed, and unknown keys are never kept."""
    ttl = 1.0
    srv = api_server_factory(api_key_cache_s=ttl)
    key = new_api_key(srv.env, "read")
    url = "/collections/facades/items?limit=1"
    with httpx.Client(base_url=srv.base, headers={"Authorization": f"Bearer {key}"}, timeout=60) as c:
        assert c.get(url).status_code == 200  # looked up in the database, now cached
        assert c.get(url).status_code == 200  # from the cache
        listed = subprocess.run(
            [citytherm_exe(), "apikey", "list", "--json"],
            env=srv.env,
            capture_output=True,
            text=True,
            check=True,
        )
        (row,) = [k for k in json.loads(listed.stdout) if key.startswith(k["prefix"])]
        subprocess.run([citytherm_exe(), "apikey", "revoke", str(row["id"])], env=srv.env, check=True)
        time.sleep(ttl + 0.5)  # the entry has expired: the next request asks the database again
        r = c.get(url)
        assert_problem(r, 401)
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert_problem(c.get(url), 401)  # a revoked key is not kept
    with httpx.Client(base_url=srv.base, timeout=60) as c:
        for _ in range(2):  # an unknown key is refused every time
            assert_problem(c.get(url, headers={"Authorization": "Bearer ct_unknown"}), 401)
