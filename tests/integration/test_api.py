"""The HTTP API served by uvicorn (`citytherm serve`) in a subprocess, over HTTP, against the real
PostGIS test database and Redis: OGC documents, API keys, job validation, job status / paging /
dismissal / results on rows, models, and an OpenAPI-driven fuzz run (uploads:
`test_api_uploads.py`). Job execution belongs to the workers: these tests check the API's own
behaviour."""

from __future__ import annotations

import io
import json
import subprocess
import time
import uuid
from pathlib import Path

import httpx
import pytest
from sqlalchemy import text
from sqlalchemy.orm import Session

from db.jobs import add_units, create_job, set_job_status
from tests.integration.conftest import (
    ApiServer,
    assert_problem,
    citytherm_exe,
    new_api_key,
    package_variant,
    ready_api_model,
    tar_gz,
    upload_parts,
)
from workers.pipeline.synth import BUNDLED_MODEL

pytestmark = pytest.mark.integration


# -- documents ---------------------------------------------------------------------------------
def test_landing_conformance_processes_openapi(api: ApiServer) -> None:
    with api.client("read") as c:
        links = {link["rel"]: link["href"] for link in c.get("/").json()["links"]}
        assert links["service-desc"].endswith("/openapi.json") and links["service-doc"].endswith("/docs")
        conf = c.get("/conformance").json()["conformsTo"]
        assert "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/core" in conf
        procs = c.get("/processes").json()["processes"]
        assert [p["id"] for p in procs] == ["texture"]
        desc = c.get("/processes/texture").json()
        assert set(desc["inputs"]) == {
            "model", "sequence", "theme", "resolution", "buildings", "refine", "calibrate", "orient",
            "orientation", "rgb", "anomalies",
        }  # fmt: skip
        assert desc["inputs"]["orientation"]["schema"]["enum"] == ["edges", "sfm", "both"]
        assert desc["inputs"]["model"]["minOccurs"] == 1 and desc["inputs"]["theme"]["minOccurs"] == 0
        assert desc["outputs"]["results"]["schema"]["contentMediaType"] == "application/zip"
        assert_problem(c.get("/processes/other"), 404)
        assert_problem(c.get("/no/such/route"), 404)
        spec = c.get("/openapi.json").json()
        assert (
            "/processes/{processID}/execution" in spec["paths"] and "Problem" in spec["components"]["schemas"]
        )
        assert c.get("/docs").status_code == 200


# -- access ------------------------------------------------------------------------------------
def test_api_keys(api: ApiServer, make_api) -> None:
    with api.client(None) as c:
        # discovery and health checks need no key; everything else does
        assert c.get("/").status_code == 200 and c.get("/conformance").status_code == 200
        r = c.get("/processes")
        assert_problem(r, 401)
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert_problem(c.get("/processes", headers={"Authorization": "Bearer ct_wrong"}), 401)
        assert_problem(c.post("/sequences", headers={"Authorization": f"Bearer {api.keys['read']}"}), 403)
        assert_problem(c.delete("/models/1", headers={"Authorization": f"Bearer {api.keys['submit']}"}), 403)
        submit = {"Authorization": f"Bearer {api.keys['submit']}"}
        assert c.get("/processes", headers=submit).status_code == 200
    key = new_api_key(api.env, "read")
    with httpx.Client(base_url=api.base, headers={"Authorization": f"Bearer {key}"}) as c:
        assert c.get("/processes").status_code == 200
        cmd = [citytherm_exe(), "apikey", "list", "--json"]
        listed = subprocess.run(cmd, env=api.env, capture_output=True, text=True, check=True)
        (row,) = [k for k in json.loads(listed.stdout) if key.startswith(k["prefix"])]
        assert row["scopes"] == ["read"] and row["revoked"] is None and key not in listed.stdout
        revoke = [citytherm_exe(), "apikey", "revoke", str(row["id"])]
        subprocess.run(revoke, env=api.env, check=True, capture_output=True)
        # refused once the server's key cache (api_key_cache_s, default 5 s) lets go of it
        deadline = time.monotonic() + 30
        while c.get("/processes").status_code == 200 and time.monotonic() < deadline:
            time.sleep(0.25)
        assert_problem(c.get("/processes"), 401)  # revoked
    open_api = make_api(api_read_open="true")
    with open_api.client(None) as c:
        assert c.get("/processes").status_code == 200
        assert_problem(c.post("/sequences"), 401)
        assert_problem(c.get("/processes", headers={"Authorization": "Bearer ct_wrong"}), 401)


# -- jobs --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def berlin(db_engine) -> tuple[int, int]:
    """The Berlin model, ready: (API id, city model id)."""
    return ready_api_model(db_engine, "api-berlin")


@pytest.fixture(scope="module")
def sequences(
    api: ApiServer, synth_package: Path, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, str]:
    """Committed sequences: `same` in the model's CRS (EPSG:25833), `other` in EPSG:25832."""
    other = package_variant(synth_package, tmp_path_factory.mktemp("other"), crs="EPSG:25832")
    out = {}
    with api.client("submit") as c:
        for key, folder in (("same", synth_package), ("other", other)):
            sid = upload_parts(c, tar_gz(folder), parts=2)
            assert c.post(f"/sequences/{sid}/commit").status_code == 200
            out[key] = sid
    return out


def _execute(c: httpx.Client, **inputs: object) -> httpx.Response:
    return c.post(
        "/processes/texture/execution", json={"inputs": inputs}, headers={"Prefer": "respond-async"}
    )


def test_job_submission_validation(api: ApiServer, berlin, sequences, db_engine) -> None:
    model, _ = berlin
    with api.client("submit") as c:
        assert "model" in assert_problem(_execute(c, model=999999, sequence=sequences["same"]), 404)["detail"]
        assert (
            "sequence" in assert_problem(_execute(c, model=model, sequence=str(uuid.uuid4())), 404)["detail"]
        )
        detail = assert_problem(_execute(c, model=model, sequence=sequences["other"]), 422)["detail"]
        assert "EPSG:25832" in detail and "EPSG:25833" in detail
        for bad, name in (
            ({"resolution": -1}, "resolution"),
            ({"resolution": "fine"}, "resolution"),
            ({"refine": "perhaps"}, "refine"),
            ({"theme": "a b/c"}, "theme"),
            ({"buildings": ["NO_SUCH_BUILDING"]}, "buildings"),
            ({"colour": "red"}, "colour"),
        ):
            r = _execute(c, model=model, sequence=sequences["same"], **bad)
            assert name in assert_problem(r, 422)["detail"], bad
        assert_problem(
            c.post("/processes/texture/execution", json={"inputs": {"sequence": sequences["same"]}}), 422
        )
        body = {"inputs": {"model": model, "sequence": sequences["same"]}}
        assert_problem(c.post("/processes/other/execution", json=body), 404)
    with db_engine.begin() as conn:
        busy = conn.execute(
            text("INSERT INTO model_import (name, status) VALUES ('api-busy', 'importing') RETURNING id")
        ).scalar_one()
    with api.client("submit") as c:
        assert (
            "not ready" in assert_problem(_execute(c, model=busy, sequence=sequences["same"]), 409)["detail"]
        )
        open_sid = c.post("/sequences").json()["id"]
        assert_problem(_execute(c, model=model, sequence=open_sid), 409)


def test_job_submitted(api: ApiServer, berlin, sequences, db_engine) -> None:
    model, city_model = berlin
    with api.client("submit") as c:
        r = _execute(c, model=model, sequence=sequences["same"], resolution=5, refine=False)
        assert r.status_code == 201, r.text
        info = r.json()
        assert r.headers["location"] == f"/jobs/{info['jobID']}"
        assert info["processID"] == "texture" and info["type"] == "process"
        assert info["inputs"] == {"model": model, "sequence": sequences["same"], "theme": "thermal-ir"}
    with db_engine.connect() as conn:
        row = conn.execute(
            text("SELECT city_model_id, options FROM job WHERE id = :j"), {"j": info["jobID"]}
        ).one()
    assert row[0] == city_model and row[1]["unit"]["texel"]["resolution_px_per_m"] == 5.0
    assert row[1]["unit"]["refine"] is None


def _rows_jobs(db_engine, city_model: int, n: int) -> list[uuid.UUID]:
    with Session(db_engine) as s:
        ids = [create_job(s, model_id=city_model, theme=f"t{i}") for i in range(n)]
        s.commit()
    return ids


def test_job_status_paging_and_dismiss(api: ApiServer, berlin, db_engine) -> None:
    _, city_model = berlin
    ids = _rows_jobs(db_engine, city_model, 5)
    with Session(db_engine) as s:
        sql = "SELECT gml_id FROM building WHERE city_model_id = :m AND NOT is_part ORDER BY ordinal LIMIT 2"
        add_units(s, job_id=ids[0], building_gml_ids=list(s.execute(text(sql), {"m": city_model}).scalars()))
        set_job_status(s, job_id=ids[0], status="running", message="texturing")
        s.execute(text("UPDATE job SET stage = 'units', progress = 0.5 WHERE id = :j"), {"j": ids[0]})
        s.commit()
    with api.client("read") as c:
        info = c.get(f"/jobs/{ids[0]}").json()
        summary = (info["status"], info["stage"], info["progress"], info["message"])
        assert summary == ("running", "units", 50, "texturing")
        assert info["units"]["accepted"] == 2 and info["started"] is not None and info["finished"] is None
        seen, url = [], "/jobs?limit=2"
        while url:
            page = c.get(url).json()
            assert len(page["jobs"]) <= 2
            seen += [j["jobID"] for j in page["jobs"]]
            url = next((link["href"] for link in page["links"] if link["rel"] == "next"), None)
        assert {str(i) for i in ids} <= set(seen) and len(seen) == len(set(seen))
        running = c.get("/jobs", params={"status": "running"}).json()["jobs"]
        assert str(ids[0]) in [j["jobID"] for j in running] and {j["status"] for j in running} == {"running"}
        assert c.get("/jobs", params={"processID": "other"}).json()["jobs"] == []
        assert_problem(c.get("/jobs", params={"status": "sleeping"}), 422)
        body = assert_problem(c.get(f"/jobs/{uuid.uuid4()}"), 404)
        assert body["type"].endswith("no-such-job")
        assert_problem(c.delete(f"/jobs/{ids[1]}"), 403)
    with api.client("submit") as c:
        r = c.delete(f"/jobs/{ids[1]}")
        assert r.status_code == 200, r.text
        assert r.json()["status"] == "dismissed" and r.json()["finished"] is not None
        assert c.get(f"/jobs/{ids[1]}").json()["status"] == "dismissed"
        assert c.delete(f"/jobs/{ids[1]}").json()["status"] == "dismissed"  # again: nothing changes
        with Session(db_engine) as s:
            set_job_status(s, job_id=ids[2], status="failed", message="x")
            s.commit()
        assert_problem(c.delete(f"/jobs/{ids[2]}"), 409)  # finished
        assert_problem(c.delete(f"/jobs/{uuid.uuid4()}"), 404)


def test_results_only_after_success(api: ApiServer, berlin, db_engine) -> None:
    _, city_model = berlin
    (job,) = _rows_jobs(db_engine, city_model, 1)
    with api.client("read") as c:
        assert assert_problem(c.get(f"/jobs/{job}/results"), 409)["type"].endswith("result-not-ready")
        with Session(db_engine) as s:
            set_job_status(s, job_id=job, status="running")
            set_job_status(s, job_id=job, status="successful")
            s.commit()
        assert_problem(c.get(f"/jobs/{job}/results"), 409)  # successful, but nothing written yet
        folder = api.storage / "jobs" / str(job)
        (folder / "results").mkdir(parents=True)
        (folder / "results" / "report.json").write_text('{"ok": true}')
        (folder / "results" / "orientation.json").write_text("{}")
        (folder / "results" / "anomalies.geojson").write_text('{"type": "FeatureCollection", "features": []}')
        (folder / "results.zip").write_bytes(b"PK\x05\x06" + b"\0" * 18)
        outputs = c.get(f"/jobs/{job}/results").json()
        assert outputs["results"]["type"] == "application/zip"
        assert outputs["results"]["href"].endswith(f"/jobs/{job}/results/results.zip")
        assert {k: v["type"] for k, v in outputs.items()} == {
            "results": "application/zip", "orientation": "application/json", "report": "application/json",
            "anomalies": "application/geo+json",
        }  # fmt: skip
        assert c.get(outputs["results"]["href"]).content == (folder / "results.zip").read_bytes()
        assert c.get(outputs["report"]["href"]).json() == {"ok": True}
        assert "results" in [link["rel"].rsplit("/", 1)[-1] for link in c.get(f"/jobs/{job}").json()["links"]]
        # a real file beside the results folder (the zip) is not served through a path out of it
        assert (folder / "results.zip").is_file()
        assert_problem(c.get(f"/jobs/{job}/results/..%2Fresults.zip"), 404)
        assert_problem(c.get(f"/jobs/{job}/results/results%2F..%2F..%2Fresults.zip"), 404)
        assert_problem(c.get(f"/jobs/{job}/results/missing.json"), 404)


def test_model_view_export_and_delete(api: ApiServer, db_engine) -> None:
    model, city_model = ready_api_model(db_engine, "api-delete-me")
    (job,) = _rows_jobs(db_engine, city_model, 1)
    with api.client("read") as c:
        view = c.get(f"/models/{model}").json()
        summary = (view["status"], view["crs"], view["srid"], view["buildings"])
        assert summary == ("ready", "EPSG:25833", 25833, 61)
        assert len(view["extent"]) == 6 and 390000 < view["extent"][0] < 391000
        r = c.get(f"/models/{model}/citygml")
        assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
        import zipfile

        with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
            assert "textured.gml" in zf.namelist()
        assert_problem(c.get(f"/models/{model}/citygml", params={"bbox": "1,2,x"}), 422)
        assert_problem(c.delete(f"/models/{model}"), 403)
    with api.client("admin") as c:
        assert "job" in assert_problem(c.delete(f"/models/{model}"), 409)["detail"]
        with Session(db_engine) as s:
            set_job_status(s, job_id=job, status="failed", message="test")
            s.commit()
        assert c.delete(f"/models/{model}").status_code == 204
        assert_problem(c.get(f"/models/{model}"), 404)
        assert_problem(c.delete(f"/models/{model}"), 404)
    with db_engine.connect() as conn:
        left = conn.execute(text("SELECT count(*) FROM city_model WHERE id = :m"), {"m": city_model})
        assert left.scalar() == 0


def test_models_imported_from_the_command_line_are_listed(api: ApiServer, db_engine) -> None:
    """A model imported with `citytherm import` (no upload, no `model_import` row) is adopted:
    listed `ready` with an API id that jobs can name; adopting twice makes no second row."""
    from db.importer import import_citygml

    city_model = import_citygml(db_engine, BUNDLED_MODEL, name="api-from-cli").model_id
    with api.client("read") as c:
        listed = [m for m in c.get("/models").json()["models"] if m["name"] == "api-from-cli"]
        assert len(listed) == 1 and listed[0]["status"] == "ready", listed
        view = c.get(f"/models/{listed[0]['id']}").json()
        assert (view["status"], view["buildings"]) == ("ready", 61)
        again = [m for m in c.get("/models").json()["models"] if m["name"] == "api-from-cli"]
        assert [m["id"] for m in again] == [listed[0]["id"]]
    with db_engine.connect() as conn:
        rows = conn.execute(
            text("SELECT count(*) FROM model_import WHERE city_model_id = :m"), {"m": city_model}
        ).scalar_one()
    assert rows == 1


def test_lost_imports_are_found_for_the_sweeper(db_engine) -> None:
    """An import `importing` with its upload stored and untouched for longer than the threshold is
    handed to the sweeper once (then touched); a fresh one, or one without an upload, is not."""
    from db.service_records import imports_to_requeue

    with db_engine.begin() as conn:
        ids = [
            conn.execute(
                text(
                    "INSERT INTO model_import (name, status, upload_path, updated_at) VALUES "
                    "(:n, 'importing', :p, now() - make_interval(secs => :age)) RETURNING id"
                ),
                {"n": f"api-lost-{k}", "p": p, "age": age},
            ).scalar_one()
            for k, (p, age) in enumerate((("/x/lost.gml", 600), ("/x/fresh.gml", 1), (None, 600)))
        ]
    with Session(db_engine) as s:
        first = imports_to_requeue(s, older_than_s=60)
        s.commit()
    assert ids[0] in first and ids[1] not in first and ids[2] not in first
    with Session(db_engine) as s:
        assert ids[0] not in imports_to_requeue(s, older_than_s=60)  # touched: not again at once
        s.execute(text("DELETE FROM model_import WHERE id = ANY(:i)"), {"i": ids})
        s.commit()


# -- fuzzing -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fuzz_schema(make_api):
    """The OpenAPI document of a server of its own (an admin key: every route is reachable)."""
    import schemathesis

    fuzz = make_api()
    schema = schemathesis.openapi.from_url(f"{fuzz.base}/openapi.json")
    schema.config.update(base_url=fuzz.base, headers={"Authorization": f"Bearer {fuzz.keys['admin']}"})
    return schema


def test_fuzz_finds_no_server_error(fuzz_schema) -> None:
    """Generated requests for every operation (schemathesis, from the OpenAPI document, a few
    examples each): never a 5xx, and every error a problem+json document."""
    from hypothesis import HealthCheck, given, settings

    seen = []
    for result in fuzz_schema.get_all_operations():
        operation = result.ok()

        @settings(max_examples=6, deadline=30_000, suppress_health_check=list(HealthCheck), derandomize=True)
        @given(case=operation.as_strategy())
        def call(case) -> None:
            response = case.call()
            assert response.status_code < 500, (case.method, case.path, response.status_code, response.text)
            if response.status_code >= 400 and case.method != "HEAD":
                ctype = {k.lower(): v for k, v in response.headers.items()}["content-type"]
                assert "application/problem+json" in str(ctype), response.text

        call()
        seen.append(operation.label)
    assert len(seen) >= 17, seen
