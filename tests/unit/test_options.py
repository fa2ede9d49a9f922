"""Every options class of the pipeline and the job round-trips through JSON (the service stores a
job's options with the job), and bad option documents are refused naming the field."""

from __future__ import annotations

import dataclasses
import importlib
import json
import pkgutil

import pytest

import workers.pipeline
from workers.job import RunOptions
from workers.pipeline.options import OptionsError, options_from_dict, options_to_dict
from workers.pipeline.orientation.building import CoregisterOptions, calibrated_options
from workers.pipeline.texture.texel import TexelOptions
from workers.pipeline.units import UnitOptions


def options_classes() -> list[type]:
    """Every dataclass named `...Options` defined in a module of `workers.pipeline`."""
    found: dict[str, type] = {}
    for info in pkgutil.walk_packages(workers.pipeline.__path__, "workers.pipeline."):
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if (
                name.endswith("Options")
                and isinstance(obj, type)
                and dataclasses.is_dataclass(obj)
                and obj.__module__ == module.__name__
            ):
                found[f"{obj.__module__}.{name}"] = obj
    return [found[k] for k in sorted(found)]


CLASSES = options_classes()


def test_the_walk_finds_the_stage_options() -> None:
    names = {c.__name__ for c in CLASSES}
    assert {"CoregisterOptions", "TexelOptions", "UnitOptions", "PlanOptions", "CalibrationOptions",
            "BundleOptions", "FusionOptions", "SynthOptions"} <= names


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: f"{c.__module__}.{c.__name__}")
def test_options_are_frozen_typed_and_round_trip_through_json(cls: type) -> None:
    assert cls.__dataclass_params__.frozen, f"{cls.__name__} is not frozen"  # type: ignore[attr-defined]
    for f in dataclasses.fields(cls):
        assert "object" not in str(f.type) and "Any" not in str(f.type), f"{cls.__name__}.{f.name}: {f.type}"
    default = cls()
    text = json.dumps(options_to_dict(default), allow_nan=False)
    assert options_from_dict(cls, json.loads(text)) == default


def test_run_options_round_trip_with_values_that_differ_from_the_defaults() -> None:
    opts = RunOptions.build(
        resolution_px_per_m=4.5, theme="winter", refine=True, buildings=("A", "B"), workers=3, calibrate=False
    )
    calibrated = dataclasses.replace(opts.unit, refine=calibrated_options(CoregisterOptions()))
    opts = dataclasses.replace(opts, unit=calibrated)
    back = RunOptions.from_dict(json.loads(json.dumps(opts.to_dict())))
    assert back == opts
    assert back.resolution_px_per_m == 4.5 and back.theme == "winter" and back.refine
    assert RunOptions.from_dict(RunOptions.build(refine=False).to_dict()).unit.refine is None


def test_the_library_default_is_the_command_lines_default() -> None:
    assert RunOptions().refine is True
    assert UnitOptions().refine == CoregisterOptions()


@pytest.mark.parametrize(
    ("doc", "field"),
    [
        ({"unit": {"texel": {"resolution_px_per_m": "fine"}}}, "TexelOptions.resolution_px_per_m"),
        ({"workers": 1.5}, "RunOptions.workers"),
        ({"buildings": "B1"}, "RunOptions.buildings"),
        ({"colour": "red"}, "colour"),
    ],
)
def test_bad_option_documents_name_the_field(doc: dict, field: str) -> None:
    with pytest.raises(OptionsError, match=field):
        RunOptions.from_dict(doc)


def test_values_the_dataclass_refuses_stay_refused() -> None:
    with pytest.raises(ValueError, match="resolution_px_per_m"):
        options_from_dict(TexelOptions, {"resolution_px_per_m": -1.0})
