"""The tiling of the 3D Tiles export (quadtree, geometric error by level, transforms), its pool of
writers, its errors and `citytherm export --format 3dtiles` on a folder."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from db.tiles3d import SourceError, TilesOptions, export_3dtiles, folder_source
from db.tiles3d.frames import ecef_from_enu
from db.tiles3d.images import DisplayScale, ValueScale
from db.tiles3d.source import write_source_file
from db.tiles3d.tiling import quadtree
from services.cli import app as cli_app
from tests.conftest import sample
from tests.unit.test_tiles3d_support import tileset_errors
from workers.pipeline.geometry.manifest import Radiometry


@pytest.fixture(scope="module")
def potsdam(tmp_path_factory):
    folder = tmp_path_factory.mktemp("potsdam") / "model"
    folder.mkdir()
    shutil.copy(sample("potsdam-97-buildings-citygml1-lod1.gml"), folder / "textured.gml")
    write_source_file(folder, "thermal-ir", Radiometry("degC", 0.01, -20.0), {})
    return folder


def test_quadtree_puts_every_building_in_one_leaf_and_halves_the_side_per_level():
    rng = np.random.default_rng(1)
    pts = np.concatenate([rng.normal(0, 30, (300, 2)), rng.uniform(-2000, 2000, (200, 2))])
    root = quadtree(pts, max_buildings=20, max_depth=10)
    members = sorted(i for leaf in root.leaves() for i in leaf.members)
    assert members == list(range(len(pts)))
    for leaf in root.leaves():
        assert len(leaf.members) <= 20 or leaf.level == 10
        side = root.side / 2**leaf.level
        assert leaf.side == pytest.approx(side)
        inside = pts[leaf.members]
        assert (inside >= leaf.lo - 1e-9).all() and (inside <= leaf.lo + side + 1e-9).all()


def test_geometric_error_falls_by_level_and_leaves_carry_transforms(potsdam, tmp_path):
    export_3dtiles(folder_source(potsdam), tmp_path / "t", TilesOptions(max_buildings=5))
    doc = json.loads((tmp_path / "t" / "tileset.json").read_text())
    assert tileset_errors(doc) == []
    root = doc["root"]
    assert root["refine"] == "ADD" and doc["geometricError"] > root["geometricError"] > 0
    m = np.array(root["transform"]).reshape(4, 4).T
    assert np.allclose(m, ecef_from_enu(m[:3, 3]))  # an east-north-up frame on the ellipsoid

    def walk(tile: dict, parent_error: float) -> int:
        assert tile["geometricError"] < parent_error
        if "content" in tile:
            assert tile["geometricError"] == 0 and "transform" in tile and "children" not in tile
            t = np.array(tile["transform"]).reshape(4, 4).T
            assert np.allclose(t[:3, :3], np.eye(3)) and np.abs(t[:3, 3]).max() < 5e4
            return 1
        kids = tile["children"]
        for k in kids:
            if "children" in k:
                assert k["geometricError"] == pytest.approx(tile["geometricError"] / 2)
        return sum(walk(k, tile["geometricError"]) for k in kids)

    assert walk(root, doc["geometricError"]) == len(list((tmp_path / "t").rglob("*.glb"))) > 10
    extras = doc["asset"]["extras"]["citytherm"]
    assert extras["value"]["unit"] == "K" and extras["value"]["dn_offset"] == pytest.approx(253.15)
    assert extras["heights_exact"] is False  # DHHN92 needs a geoid grid PROJ does not have here


def test_a_pool_of_writers_writes_the_same_files(potsdam, tmp_path):
    export_3dtiles(folder_source(potsdam), tmp_path / "one", TilesOptions(max_buildings=10))
    export_3dtiles(folder_source(potsdam), tmp_path / "two", TilesOptions(max_buildings=10, workers=2))
    a = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").rglob("*") if p.is_file())
    b = sorted(p.relative_to(tmp_path / "two") for p in (tmp_path / "two").rglob("*") if p.is_file())
    assert a == b and len(a) > 5
    for rel in a:
        assert (tmp_path / "one" / rel).read_bytes() == (tmp_path / "two" / rel).read_bytes(), rel


def test_value_and_display_scales():
    v = ValueScale.of(Radiometry("degC", 0.01, -40.0))
    assert v.unit == "K" and v.offset == pytest.approx(233.15) and v.metadata_scale == pytest.approx(655.35)
    assert np.isnan(v.value(np.array([0]))[0]) and v.value(np.array([4000]))[0] == pytest.approx(273.15)
    d = DisplayScale(270.0, 280.0)
    assert d.index(np.array([270.0, 275.0, 280.0, np.nan])).tolist() == [1, 128, 255, 0]
    assert d.rgb(np.array([[np.nan]])).tolist() == [[[0, 0, 0]]]
    assert len(d.legend()) == 255


def test_a_folder_that_is_no_results_folder_is_refused_by_name(tmp_path):
    with pytest.raises(SourceError, match=r"textured\.gml"):
        folder_source(tmp_path)
    shutil.copy(sample("potsdam-97-buildings-citygml1-lod1.gml"), tmp_path / "textured.gml")
    with pytest.raises(SourceError, match=r"report\.json"):
        folder_source(tmp_path)


def test_cli_exports_a_folder(potsdam, tmp_path):
    out = tmp_path / "cli"
    res = CliRunner().invoke(cli_app, ["export", "--format", "3dtiles", str(potsdam), "-o", str(out),
                                       "--range-c", "-5,25", "--max-buildings", "30"])  # fmt: skip
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "tileset.json").read_text())
    assert doc["asset"]["extras"]["citytherm"]["display"]["range"] == pytest.approx([268.15, 298.15])
    assert "heights" in res.output  # the warning about the missing geoid grid
    args = ["export", "--format", "3dtiles", str(tmp_path / "none"), "-o", str(out)]
    bad = CliRunner().invoke(cli_app, args)
    assert bad.exit_code == 1 and "export failed" in bad.output
