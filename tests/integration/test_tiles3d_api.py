"""`GET /models/{id}/3dtiles/tileset.json` and its GLBs over HTTP from a running `citytherm serve`
(real PostGIS), and `citytherm export --format 3dtiles --model` from the database: the model's
newest job with thermal textures, valid against the 3D Tiles 1.1 schemas and the Khronos glTF
validator, vertices back within 1 cm of pyproj's ECEF, served from the cache the second time."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pyproj
import pytest
from typer.testing import CliRunner

from db.citygml.reader import read_model
from db.results_import import import_results
from db.tiles3d import export_3dtiles, folder_source
from db.tiles3d.glb import read_glb
from services.cli import app as cli_app
from tests.integration.conftest import assert_problem, ready_api_model
from tests.unit.test_tiles3d_support import (
    assert_khronos_clean,
    glb_ecef,
    make_textured_results,
    metadata_errors,
    tileset_errors,
)
from workers.pipeline.geometry.crs import resolve_crs

pytestmark = [pytest.mark.integration, pytest.mark.slow]


@pytest.fixture(scope="module")
def textured_model(db_engine, tmp_path_factory):
    """The bundled Berlin model as a ready API model with a job's results imported:
    (API model id, city model id, results folder)."""
    results = make_textured_results(tmp_path_factory.mktemp("tiles3d-api-job"))
    api_id, model_id = ready_api_model(db_engine, "tiles3d-berlin")
    import_results(db_engine, results, model=model_id)
    return api_id, model_id, results


@pytest.fixture(scope="module")
def server(api_server_factory):
    return api_server_factory()


def _download(client, api_id: int, folder: Path) -> dict:
    r = client.get(f"/models/{api_id}/3dtiles/tileset.json")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("application/json")
    doc = r.json()
    (folder / "tileset.json").write_bytes(r.content)
    uris: list[str] = []

    def walk(tile: dict) -> None:
        if "content" in tile:
            uris.append(tile["content"]["uri"])
        for c in tile.get("children", []):
            walk(c)

    walk(doc["root"])
    for uri in uris:
        g = client.get(f"/models/{api_id}/3dtiles/{uri}")
        assert g.status_code == 200, g.text
        assert g.headers["content-type"] == "model/gltf-binary"
        (folder / uri).parent.mkdir(parents=True, exist_ok=True)
        (folder / uri).write_bytes(g.content)
    return doc


def test_the_api_serves_a_valid_tileset_of_the_newest_job(server, textured_model, tmp_path):
    api_id, _, results = textured_model
    with server.client("read") as client:
        t0 = time.perf_counter()
        doc = _download(client, api_id, tmp_path)
        first = time.perf_counter() - t0
        assert tileset_errors(doc) == []
        extras = doc["asset"]["extras"]["citytherm"]
        assert extras["theme"] == "thermal-ir" and extras["value"]["unit"] == "K"
        # the database's figures give the same colour range as the results folder's report
        folder = export_3dtiles(folder_source(results), tmp_path / "from-folder")
        assert extras["display"]["range"] == pytest.approx([folder.display.lo, folder.display.hi])
        glbs = sorted(tmp_path.rglob("*.glb"))
        assert_khronos_clean(glbs)
        contents = glb_ecef(doc, tmp_path)
        assert all(metadata_errors(gltf) == [] for gltf, _, _ in contents.values())
        # every vertex of the job's textured buildings comes back within 1 cm of pyproj's ECEF
        header, buildings = read_model(results / "textured.gml")
        crs = resolve_crs(header.srs_name or "").to_3d()
        t = pyproj.Transformer.from_crs(crs, "EPSG:4978", always_xy=True)
        got = np.concatenate([e for _, _, e in contents.values()])
        pts = np.concatenate([p.exterior.coords for b in buildings for p in b.iter_polygons()])
        want = np.stack(t.transform(pts[:, 0], pts[:, 1], pts[:, 2]), axis=-1)
        for k in range(0, len(want), 500):
            d = np.linalg.norm(want[k : k + 500, None, :] - got[None, :, :], axis=2).min(axis=1)
            assert d.max() < 0.01
        # textures: display and value images, one property texture per textured primitive
        n_tex = sum(len(g["extensions"]["EXT_structural_metadata"].get("propertyTextures", []))
                    for g, _, _ in contents.values())  # fmt: skip
        assert n_tex >= 1
        # second request: from the cache, same bytes
        t0 = time.perf_counter()
        again = client.get(f"/models/{api_id}/3dtiles/tileset.json")
        assert again.status_code == 200 and again.content == (tmp_path / "tileset.json").read_bytes()
        assert time.perf_counter() - t0 < first


def test_the_api_refuses_what_it_cannot_serve(server, textured_model, db_engine):
    api_id, _, _ = textured_model
    with server.client("read") as client:
        assert_problem(client.get("/models/999999/3dtiles/tileset.json"), 404)
        r = client.get(f"/models/{api_id}/3dtiles/../../../etc/passwd")
        assert r.status_code == 404
        assert client.get(f"/models/{api_id}/3dtiles/content/9/9_9.glb").status_code == 404
        assert client.get(f"/models/{api_id}/3dtiles/content/%00.glb").status_code == 404
        bare, _ = ready_api_model(db_engine, "tiles3d-bare")  # a model without any job
        assert_problem(client.get(f"/models/{bare}/3dtiles/tileset.json"), 404)
    with server.client(None) as anonymous:
        assert anonymous.get(f"/models/{api_id}/3dtiles/tileset.json").status_code == 401


def test_cli_exports_a_model_of_the_database(textured_model, migrated_db, tmp_path):
    _, model_id, _ = textured_model
    out = tmp_path / "tiles"
    args = ["export", "--format", "3dtiles", "--model", str(model_id), "-o", str(out)]
    res = CliRunner().invoke(cli_app, [*args, "--database-url", migrated_db])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "tileset.json").read_text())
    assert tileset_errors(doc) == []
    gltf, _ = read_glb(next(out.rglob("*.glb")).read_bytes())
    assert "EXT_structural_metadata" in gltf["extensions"]
