"""The database commands end to end: `citytherm db current|upgrade`, `import`, `export`."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from db.citygml.reader import read_model
from db.citygml.validate import validate_citygml2
from db.migrations import head_revision
from services.cli import app
from tests.conftest import DATA

pytestmark = pytest.mark.integration


def test_cli_import_export(migrated_db, tmp_path) -> None:
    runner = CliRunner()
    url = ["--database-url", migrated_db]
    res = runner.invoke(app, ["db", "upgrade", *url])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["db", "current", *url])
    assert res.exit_code == 0 and f"current: {head_revision()}" in res.output
    gml = DATA / "potsdam-97-buildings-citygml1-lod1.gml"
    res = runner.invoke(app, ["import", str(gml), "--name", "cli-potsdam", *url])
    assert res.exit_code == 0, res.output
    assert "97 buildings" in res.output
    res = runner.invoke(app, ["import", str(gml), "--name", "cli-potsdam", *url])
    assert res.exit_code == 1 and "exists already" in res.output
    _, buildings = read_model(gml)
    lo = min(b.bounds()[0][0] for b in buildings), min(b.bounds()[0][1] for b in buildings)
    hi = max(b.bounds()[1][0] for b in buildings), max(b.bounds()[1][1] for b in buildings)
    bbox = f"{lo[0]},{lo[1]},{(lo[0] + hi[0]) / 2},{hi[1]}"
    res = runner.invoke(app, ["export", "--model", "cli-potsdam", "--bbox", bbox, "-o", str(tmp_path), *url])
    assert res.exit_code == 0, res.output
    _, back = read_model(tmp_path / "textured.gml")
    assert 0 < len(back) < len(buildings)
    assert validate_citygml2(tmp_path / "textured.gml") == []
    res = runner.invoke(
        app, ["export", "--model", "cli-potsdam", "--bbox", "1,2,3", "-o", str(tmp_path), *url]
    )
    assert res.exit_code != 0
    res = runner.invoke(app, ["export", "--model", "no-such-model", "-o", str(tmp_path), *url])
    assert res.exit_code == 1 and "not found" in res.output
