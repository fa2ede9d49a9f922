"""Shared test data: the real CityGML samples, all inside the repository.

`tests/data/` holds five of them (sources and licences in its README); the sixth,
`berlin-61-buildings-citygml1-lod2.gml`, is the synthetic demo's bundled model
(`workers.pipeline.synth.BUNDLED_MODEL`) and is not copied a second time.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from workers.pipeline.synth import BUNDLED_MODEL

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "tests" / "data"
# every real sample, sorted by file name
SAMPLE_FILES: list[Path] = sorted([*DATA.glob("*.gml"), BUNDLED_MODEL], key=lambda p: p.name)


def sample(name: str) -> Path:
    """A real sample by its file name (`DATA / name`, or the bundled Berlin model)."""
    for p in SAMPLE_FILES:
        if p.name == name:
            return p
    raise FileNotFoundError(f"no CityGML sample {name!r} in {DATA} or {BUNDLED_MODEL.parent}")


def replicated_nrw(dst: Path, copies: int) -> Path:
    """The NRW tile replicated `copies` times with new gml:ids into one file `dst` (109 buildings,
    55 parts a copy), as the benchmarks build it (`bench/citygml_io.make_replicated_model`)."""
    spec = importlib.util.spec_from_file_location("citygml_io_bench", REPO / "bench" / "citygml_io.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.make_replicated_model(DATA / "nrw-tile-5659-citygml1-lod2.gml", dst, copies)

