"""The manifest's optional `conditions` (outside air temperature, recording time): parsed, checked
with errors naming the field, written back, and carried into `report.json`."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from db.sequence_manifest import PackageError, manifest_to_dict, parse_manifest
from db.sequence_package import open_package, write_package
from tests.unit.test_sequence_package import dn_frames, make_manifest
from workers.pipeline.geometry.manifest import Conditions


def test_conditions_round_trip_through_a_package(tmp_path: Path) -> None:
    cond = Conditions(air_temperature_c=-3.5, recorded_at="2025-01-15T21:30:00+01:00")
    pkg = write_package(tmp_path / "pkg", replace(make_manifest(), conditions=cond), dn_frames())
    with open_package(pkg) as p:
        assert p.manifest.conditions == cond
        assert p.manifest.conditions.air_temperature_k == pytest.approx(269.65)
    assert "conditions" not in manifest_to_dict(make_manifest())  # optional: absent stays absent


@pytest.mark.parametrize(
    ("conditions", "field"),
    [
        ({"air_temperature_c": "cold"}, "conditions.air_temperature_c"),
        ({"air_temperature_c": float("nan")}, "conditions.air_temperature_c"),
        ({"air_temperature_c": 270.0}, "conditions.air_temperature_c"),  # kelvin given
        ({"air_temperature_k": 270.0}, "conditions.air_temperature_k"),
        ({"recorded_at": "2025-01-15 21:30"}, "conditions.recorded_at"),
        ({"recorded_at": "2025-13-15T21:30:00Z"}, "conditions.recorded_at"),
        ([1.0], "conditions"),
    ],
)
def test_bad_conditions_are_refused_naming_the_field(conditions: object, field: str) -> None:
    d = manifest_to_dict(make_manifest())
    d["conditions"] = conditions
    with pytest.raises(PackageError) as exc:
        parse_manifest(d)
    assert exc.value.field == field and str(exc.value).startswith(field)
