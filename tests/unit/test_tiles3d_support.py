"""What the 3D Tiles tests share: the validators no one here wrote, a small textured results folder
made by the real pipeline, and the way back from a GLB vertex to ECEF; plus the tests that the
validators do reject broken input (a validator that passes everything proves nothing).

- `tileset_errors`: the 3D Tiles 1.1 JSON schemas (`tests/data/schemas/3d-tiles/`, copied
  unchanged from the specification) with `jsonschema` Draft 2020-12 and a local `referencing`
  registry: no network.
- `khronos_reports`: the Khronos glTF validator (npm `gltf-validator`, installed by
  `npm ci` in `tools/gltf-validator/`) run by node on each GLB. Missing node or validator: the test
  fails under CI (`CI` set) and is skipped locally, saying why.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from jsonschema import Draft202012Validator
from referencing import Registry, Resource
from referencing.jsonschema import DRAFT202012

from db.tiles3d.frames import Y_UP_TO_Z_UP
from db.tiles3d.glb import GltfBuilder, accessor_array, read_glb

REPO = Path(__file__).resolve().parents[2]
SCHEMAS = REPO / "tests" / "data" / "schemas" / "3d-tiles"
VALIDATOR_DIR = REPO / "tools" / "gltf-validator"
BASE_URI = "https://schemas.citytherm.invalid/3d-tiles/"


def _resource(path: Path) -> Resource:
    return Resource.from_contents(json.loads(path.read_text()), DRAFT202012)


@lru_cache(maxsize=4)
def _validator(name: str) -> Draft202012Validator:
    resources = [
        (BASE_URI + p.relative_to(SCHEMAS).as_posix(), _resource(p)) for p in SCHEMAS.rglob("*.schema.json")
    ]
    registry = Registry().with_resources(resources)
    return Draft202012Validator({"$ref": BASE_URI + name}, registry=registry)


def schema_errors(doc: Any, name: str = "tileset.schema.json") -> list[str]:
    """Messages of every schema violation of `doc` against schema file `name` (3D Tiles 1.1)."""
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in _validator(name).iter_errors(doc)]


def tileset_errors(doc: Any) -> list[str]:
    """Schema violations of a tileset JSON."""
    return schema_errors(doc, "tileset.schema.json")


def metadata_errors(gltf: dict[str, Any]) -> list[str]:
    """Violations of a glTF's `EXT_structural_metadata` schema and property tables against the 3D
    Metadata schemas of 3D Tiles 1.1 (the extension implements them)."""
    ext = gltf["extensions"]["EXT_structural_metadata"]
    errors = schema_errors(ext["schema"], "Schema/schema.schema.json")
    for t in ext.get("propertyTables", []):
        errors += schema_errors(t, "PropertyTable/propertyTable.schema.json")
    return errors


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def require_khronos() -> list[str]:
    """The command that runs the Khronos validator, or fail (CI) / skip (locally) saying why."""
    node = shutil.which("node")
    script = VALIDATOR_DIR / "validate.mjs"
    installed = (VALIDATOR_DIR / "node_modules" / "gltf-validator" / "package.json").is_file()
    reason = None
    if node is None:
        reason = "node is not installed (Debian: apt-get install nodejs npm)"
    elif not installed:
        reason = f"gltf-validator is not installed: cd {VALIDATOR_DIR} && npm ci"
    if reason is not None:
        if _in_ci():
            pytest.fail(f"the Khronos glTF validator is needed under CI: {reason}")
        pytest.skip(reason)
    return [str(node), str(script)]


def khronos_reports(paths: list[Path]) -> list[dict[str, Any]]:
    """The Khronos validator's report of each GLB (`numErrors`, `messages`, ...)."""
    cmd = require_khronos()
    out = subprocess.run([*cmd, *map(str, paths)], capture_output=True, text=True, timeout=300, check=True)
    return json.loads(out.stdout)


def assert_khronos_clean(paths: list[Path]) -> None:
    """Every GLB passes the Khronos validator without an error."""
    assert paths
    for r in khronos_reports(paths):
        errors = [m for m in r["messages"] if m["severity"] == 0]
        assert r["numErrors"] == 0 and not errors, (r["file"], errors[:10])


def glb_ecef(tileset: dict[str, Any], folder: Path) -> dict[str, tuple[dict, bytes, np.ndarray]]:
    """content URI -> (glTF JSON, BIN chunk, POSITION back in ECEF `(V, 3)` float64): root
    transform · tile transforms · Y_UP_TO_Z_UP · node matrix (none) · position."""
    out: dict[str, tuple[dict, bytes, np.ndarray]] = {}

    def walk(tile: dict[str, Any], parent: np.ndarray) -> None:
        m = parent @ np.array(tile.get("transform", np.eye(4).T.reshape(-1).tolist())).reshape(4, 4).T
        if "content" in tile:
            uri = tile["content"]["uri"]
            doc, blob = read_glb((folder / uri).read_bytes())
            node = doc["nodes"][0]
            assert "matrix" not in node and "translation" not in node
            prim = doc["meshes"][node["mesh"]]["primitives"][0]
            p = accessor_array(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
            full = m @ Y_UP_TO_Z_UP
            out[uri] = (doc, blob, p @ full[:3, :3].T + full[:3, 3])
        for child in tile.get("children", []):
            walk(child, m)

    walk(tileset["root"], np.eye(4))
    return out


def make_textured_results(folder: Path) -> Path:
    """A small results folder by the real pipeline: a synthetic error-free drive of 8 frames past
    2 buildings of the bundled Berlin model (EPSG:25833), 5 texels per metre. Returns its path."""
    from db.citygml.reader import read_model
    from db.synth_files import write_synthetic_package
    from workers.job import RunOptions
    from workers.pipeline.synth import BUNDLED_MODEL, ErrorOptions, SynthOptions, synthesize
    from workers.run import run_job

    _, buildings = read_model(BUNDLED_MODEL)
    opts = SynthOptions(n_frames=8, seed=3, buildings=2, frame_interval_s=0.2,
                        errors=ErrorOptions(enabled=False), model_path=str(BUNDLED_MODEL))  # fmt: skip
    pkg = write_synthetic_package(synthesize(buildings, opts), folder / "seq")
    out = folder / "results"
    run_job(BUNDLED_MODEL, pkg, out, RunOptions.build(resolution_px_per_m=5, refine=False, display=False))
    return out


def test_schemas_reject_a_broken_tileset():
    box = [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]
    good = {"asset": {"version": "1.1"}, "geometricError": 10.0,
            "root": {"boundingVolume": {"box": box}, "geometricError": 0}}  # fmt: skip
    assert tileset_errors(good) == []
    assert tileset_errors({**good, "asset": {"version": 1.1}})
    assert tileset_errors({**good, "root": {**good["root"], "boundingVolume": {"box": [0, 0, 0]}}})
    assert tileset_errors({**good, "geometricError": -1})
    assert tileset_errors({k: v for k, v in good.items() if k != "root"})


def test_khronos_validator_reports_errors_in_a_broken_glb(tmp_path):
    g = GltfBuilder()
    pos = g.accessor(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), bounds=True)
    g.add("meshes", {"primitives": [{"attributes": {"POSITION": pos}, "indices": 7}]})  # no accessor 7
    g.add("nodes", {"mesh": 0})
    g.doc["scenes"], g.doc["scene"] = [{"nodes": [0]}], 0
    bad = tmp_path / "bad.glb"
    bad.write_bytes(g.glb())
    good = tmp_path / "good.glb"
    del g.doc["meshes"][0]["primitives"][0]["indices"]
    good.write_bytes(g.glb())
    reports = {Path(r["file"]).name: r for r in khronos_reports([bad, good])}
    assert reports["bad.glb"]["numErrors"] > 0
    assert reports["good.glb"]["numErrors"] == 0, reports["good.glb"]["messages"]
