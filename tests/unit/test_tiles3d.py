"""3D Tiles export (`db.tiles3d`, issue 17 item 2) of real CityGML buildings: tilesets valid
against the 3D Tiles 1.1 schemas, GLBs clean in the Khronos validator, vertices back in ECEF
equal to pyproj's within 1 cm, texels back to their temperature within 0.01 K."""

from __future__ import annotations

import json
import shutil
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import pyproj
import pytest

from db.citygml.reader import read_model
from db.results_folder.read import iter_surface_textures, report_radiometry
from db.tiles3d import TilesOptions, export_3dtiles, folder_source
from db.tiles3d.glb import accessor_array, view_bytes
from db.tiles3d.mesh import building_mesh
from db.tiles3d.source import write_source_file
from tests.conftest import sample
from tests.unit.test_tiles3d_support import (
    assert_khronos_clean,
    glb_ecef,
    make_textured_results,
    metadata_errors,
    tileset_errors,
)
from workers.pipeline.geometry.crs import resolve_crs
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.geometry.polygons import fit_plane


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    return make_textured_results(tmp_path_factory.mktemp("tiles3d-job"))


@pytest.fixture(scope="module")
def tiles(results, tmp_path_factory):
    out = tmp_path_factory.mktemp("tiles3d") / "tiles"
    summary = export_3dtiles(folder_source(results), out, TilesOptions(max_buildings=2))
    return out, summary


@lru_cache(maxsize=8)
def _reference(srs_name: str) -> pyproj.Transformer:
    crs = resolve_crs(srs_name)
    return pyproj.Transformer.from_crs(crs if crs.is_compound else crs.to_3d(), "EPSG:4978", always_xy=True)


def _pyproj_ecef(srs_name: str, xyz: np.ndarray) -> np.ndarray:
    """Reference: pyproj's own transformation of the model CRS (3D) to EPSG:4978."""
    return np.stack(_reference(srs_name).transform(xyz[:, 0], xyz[:, 1], xyz[:, 2]), axis=-1)


def _model_folder(src: Path, folder: Path) -> Path:
    """A real CityGML file as an (untextured) export folder."""
    folder.mkdir(parents=True)
    shutil.copy(src, folder / "textured.gml")
    write_source_file(folder, "thermal-ir", Radiometry(), {})
    return folder


def _assert_vertices_round_trip(gml: Path, out: Path, every: int = 1) -> int:
    """Every `every`-th polygon's exterior vertices, as pyproj puts them in ECEF, are within 1 cm of
    a vertex of the surface with that gml:id in the GLBs (found by feature id). Returns checks."""
    header, buildings = read_model(gml)
    tileset = json.loads((out / "tileset.json").read_text())
    by_surface: dict[str, np.ndarray] = {}
    for doc, blob, ecef in glb_ecef(tileset, out).values():
        prim = doc["meshes"][0]["primitives"][0]
        fid = accessor_array(doc, blob, prim["attributes"]["_FEATURE_ID_0"]).astype(int)
        table = doc["extensions"]["EXT_structural_metadata"]["propertyTables"][0]["properties"]["surface"]
        raw = view_bytes(doc, blob, table["values"])
        offs = np.frombuffer(view_bytes(doc, blob, table["stringOffsets"]), dtype=np.uint32)
        for k in range(len(offs) - 1):
            by_surface[raw[offs[k] : offs[k + 1]].decode()] = ecef[fid == k]
    checked = 0
    polys = [p for b in buildings for p in b.iter_polygons()]
    for p in polys[::every]:
        got = by_surface.get(p.id)
        if got is None or not len(got):
            continue  # degenerate polygons have no triangles
        want = _pyproj_ecef(header.srs_name or "", p.exterior.coords)
        d = np.linalg.norm(want[:, None, :] - got[None, :, :], axis=2).min(axis=1)
        assert d.max() < 0.01, (p.id, d.max())
        checked += len(want)
    return checked


@pytest.mark.slow
def test_tileset_validates_and_every_glb_passes_the_khronos_validator(tiles):
    out, summary = tiles
    doc = json.loads((out / "tileset.json").read_text())
    assert tileset_errors(doc) == []
    assert doc["asset"]["version"] == "1.1" and doc["root"]["refine"] == "ADD"
    glbs = sorted(out.rglob("*.glb"))
    assert len(glbs) == summary.tiles > 1  # max_buildings=2: a real quadtree
    assert_khronos_clean(glbs)
    for _, (gltf, _, _) in glb_ecef(doc, out).items():
        assert metadata_errors(gltf) == []
    assert summary.images > 0 and summary.exact_heights


@pytest.mark.slow
def test_known_vertices_of_the_textured_berlin_buildings_come_back_to_pyproj_ecef_within_1cm(results, tiles):
    out, _ = tiles
    assert _assert_vertices_round_trip(results / "textured.gml", out) > 100


@pytest.mark.slow
def test_texels_map_back_to_their_temperature_within_0_01_k(results, tiles):
    """Points on the GLB's triangles: their UV picks a texel of the value image, decoded with the
    property's scale and offset; the same centroid, taken back to the model CRS, falls into a
    texel of the polygon's own texel grid (`iter_surface_textures`, an independent path)."""
    out, _ = tiles
    rad = report_radiometry(json.loads((results / "report.json").read_text()))
    grids = {s.polygon.id: s for s in iter_surface_textures(results, rad)}
    tileset = json.loads((out / "tileset.json").read_text())
    srs = json.loads((out / "tileset.json").read_text())["asset"]["extras"]["citytherm"]["crs"]
    back = pyproj.Transformer.from_crs("EPSG:4978", resolve_crs(srs).to_3d(), always_xy=True)
    compared = 0
    rng = np.random.default_rng(7)
    for doc, blob, ecef in glb_ecef(tileset, out).values():
        meta = doc["extensions"]["EXT_structural_metadata"]
        prop = meta["schema"]["classes"]["thermal"]["properties"]["temperature"]
        names = _strings(doc, blob, meta["propertyTables"][0]["properties"]["surface"])
        for prim in doc["meshes"][0]["primitives"]:
            if "EXT_structural_metadata" not in prim.get("extensions", {}):
                continue
            k_tex = prim["extensions"]["EXT_structural_metadata"]["propertyTextures"][0]
            ptex = meta["propertyTextures"][k_tex]
            tex = doc["textures"][ptex["properties"]["temperature"]["index"]]
            png = view_bytes(doc, blob, doc["images"][tex["source"]]["bufferView"])
            rgb = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)[..., ::-1]
            dn_img = rgb[..., 0].astype(np.int64) + 256 * rgb[..., 1].astype(np.int64)
            H, W = dn_img.shape
            uv = accessor_array(doc, blob, prim["attributes"]["TEXCOORD_0"]).astype(np.float64)
            fid = accessor_array(doc, blob, prim["attributes"]["_FEATURE_ID_0"]).astype(int)
            tris = accessor_array(doc, blob, prim["indices"]).reshape(-1, 3)
            tris = np.repeat(tris, 40, axis=0)  # 40 random points in each triangle (barycentric)
            w = rng.dirichlet(np.ones(3), len(tris))
            c_uv = np.einsum("kj,kjc->kc", w, uv[tris])
            c_ecef = np.einsum("kj,kjc->kc", w, ecef[tris])
            x, y, z = back.transform(c_ecef[:, 0], c_ecef[:, 1], c_ecef[:, 2])
            c_model = np.stack([x, y, z], axis=-1)
            for k in range(len(tris)):
                s = grids.get(names[fid[tris[k, 0]]])
                if s is None:
                    continue
                gx, gy = s.grid.raster_xy(c_model[k : k + 1])[0]
                row, col = int(np.floor(gy)), int(np.floor(gx))
                if not (0.2 < gx % 1 < 0.8 and 0.2 < gy % 1 < 0.8):
                    continue  # near a texel border: the two paths may round to neighbours
                if not (0 <= row < s.value.shape[0] and 0 <= col < s.value.shape[1]):
                    continue
                want = s.value[row, col]
                dn = dn_img[int(c_uv[k, 1] * H), int(c_uv[k, 0] * W)]
                if not np.isfinite(want) or dn == 0:
                    continue
                got = prop["offset"] + prop["scale"] * dn / 65535.0
                assert abs(got - want) < 0.01, (names[fid[tris[k, 0]]], got, want)
                compared += 1
    assert compared > 20


def _strings(doc: dict, blob: bytes, prop: dict) -> list[str]:
    raw = view_bytes(doc, blob, prop["values"])
    offs = np.frombuffer(view_bytes(doc, blob, prop["stringOffsets"]), dtype=np.uint32)
    return [raw[offs[k] : offs[k + 1]].decode() for k in range(len(offs) - 1)]


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, every",
    [("nrw-tile-5659-citygml1-lod2.gml", 7), ("potsdam-97-buildings-citygml1-lod1.gml", 3),
     ("bavaria-1-building-citygml2-lod2.gml", 1)],
)  # fmt: skip
def test_real_models_in_compound_and_adv_crs_come_back_within_1cm_and_validate(tmp_path, name, every):
    """NRW (AdV URN, DHHN2016 heights), Potsdam (OGC compound URN, DHHN92) and Bavaria (plain
    EPSG:25832, polygons with holes): untextured export in several tiles."""
    src = _model_folder(sample(name), tmp_path / "model")
    out = tmp_path / "tiles"
    export_3dtiles(folder_source(src), out, TilesOptions(max_buildings=8))
    assert tileset_errors(json.loads((out / "tileset.json").read_text())) == []
    assert _assert_vertices_round_trip(src / "textured.gml", out, every) > 30
    assert_khronos_clean(sorted(out.rglob("*.glb"))[:20])


def test_holes_are_respected_and_uv_is_s_and_one_minus_t():
    """Bavaria's polygons with holes: the triangles cover the polygon's area less the holes; a
    texture target's (s, t) become (s, 1 - t)."""
    from workers.pipeline.geometry.citymodel import Appearance, Building, ParameterizedTexture, TextureTarget

    _, (b,) = read_model(sample("bavaria-1-building-citygml2-lod2.gml"))
    holed = [p for p in b.iter_polygons() if p.interiors]
    assert holed
    p = holed[0]
    st = {r.id: np.c_[np.linspace(0.1, 0.9, len(r.coords)), np.linspace(0.2, 0.7, len(r.coords))]
          for r in p.rings}  # fmt: skip
    tex = ParameterizedTexture("t", "textures/x.png", (TextureTarget(p.id, st),))
    m = building_mesh(Building(b.id, (p,), appearances=(Appearance("thermal-ir", (tex,)),)), "thermal-ir")
    v, t = m.vertices, m.triangles
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1).sum()
    plane = fit_plane(p)
    assert plane is not None and abs(area - plane.area) < 1e-6 * max(plane.area, 1.0)
    assert (m.triangle_image == 0).all()
    n_ext = len(p.exterior.coords) - 1
    assert np.allclose(m.uv[:n_ext, 0], st[p.exterior.id][:n_ext, 0])
    assert np.allclose(m.uv[:n_ext, 1], 1.0 - st[p.exterior.id][:n_ext, 1])
