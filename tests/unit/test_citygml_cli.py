"""`citytherm model info` and `citytherm model convert`."""

from __future__ import annotations

from pathlib import Path

import typer
from typer.testing import CliRunner

from db.citygml import read_model, validate_citygml2
from services.cli import model_cmd
from tests.conftest import DATA


def _app() -> typer.Typer:
    app = typer.Typer()
    model_cmd.register(app)

    @app.callback()
    def _root() -> None:
        """test root"""

    return app


def test_info_table() -> None:
    result = CliRunner().invoke(_app(), ["model", "info", str(DATA / "nrw-tile-5659-citygml1-lod2.gml")],
                                env={"COLUMNS": "200"})  # fmt: skip
    assert result.exit_code == 0, result.output
    out = result.output
    assert "1.0" in out and "urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH*GCG2016" in out
    for label, n in [
        ("buildings", 109),
        ("building parts", 55),
        ("WallSurface", 951),
        ("ClosureSurface", 126),
    ]:
        line = next(ln for ln in out.splitlines() if f" {label} " in ln)
        assert str(n) in line, line
    assert "non_planar" in out


def test_info_error_exit_code(tmp_path: Path) -> None:
    bad = tmp_path / "bad.gml"
    bad.write_text("<notcitygml/>")
    result = CliRunner().invoke(_app(), ["model", "info", str(bad)], env={"COLUMNS": "300"})
    assert result.exit_code == 1 and "not a CityGML document" in result.output


def test_convert_citygml3_to_2(tmp_path: Path) -> None:
    out = tmp_path / "fzk2.gml"
    src = DATA / "fzk-haus-citygml3-lod2.gml"
    result = CliRunner().invoke(_app(), ["model", "convert", str(src), str(out), "--validate"])
    assert result.exit_code == 0, result.output
    assert validate_citygml2(out) == []
    header, buildings = read_model(out)
    assert header.version == "2.0"
    assert [p.id for p in buildings[0].polygons] == [p.id for p in read_model(src)[1][0].polygons]
