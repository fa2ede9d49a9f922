"""Shared test data: the real CityGML samples, all inside the repository.

`tests/data/` holds five of them (sources and licences in its README); the sixth,
`berlin-61-buildings-citygml1-lod2.gml`, is the synthetic demo's bundled model
(`workers.pipeline.synth.BUNDLED_MODEL`) and is not copied a second time.
"""

from __future__ import annotations

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
