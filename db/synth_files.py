"""Files of the synthetic scene generator (`workers.pipeline.synth`): a package and its truth.

In: a `SynthResult`, paths. Out: a sequence package folder (via `db.sequence_package.
write_package`: `sequence.json`, 16-bit frames, `imu.csv`, optional `gcps.json`) and the truth
JSON (`docs/synth-truth.md`) written next to (not inside) it (with `SynthOptions.rgb`, the
package also holds the RGB frames `rgb/NNNNNN.png` and its `rgb_camera` section); `load_truth`
reads a truth file back; `load_buildings` reads the CityGML model a truth names (or rebuilds
the procedural block).
The generator itself is pure; its files live here, with the other file formats.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path

import numpy as np

from db.citygml.reader import read_model
from db.sequence_package import write_package
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.synth.common import SynthError
from workers.pipeline.synth.procedural import procedural_block
from workers.pipeline.synth.scene import SynthResult
from workers.pipeline.synth.truth import SynthTruth


def save_truth(truth: SynthTruth, path: str | os.PathLike[str]) -> Path:
    """Write `truth` as JSON to `path` (parents created). Returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(truth.to_dict(), indent=1), encoding="utf-8")
    return p


def load_truth(path: str | os.PathLike[str]) -> SynthTruth:
    """Read a truth file (`citytherm-synth-truth/1`); `SynthError` names the file on failure."""
    p = Path(path)
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise SynthError(f"{p}: cannot read the truth file ({exc})") from exc
    try:
        return SynthTruth.from_dict(d)
    except SynthError as exc:
        raise SynthError(f"{p}: {exc}") from exc


def write_synthetic_package(
    result: SynthResult,
    out_dir: str | os.PathLike[str],
    truth_path: str | os.PathLike[str] | None = None,
    frames: Iterable[np.ndarray] | None = None,
) -> Path:
    """Render every frame and write the package folder `out_dir`; write the truth to
    `truth_path` (default: `<out_dir>.truth.json`, next to the package). Returns the package
    folder. The truth's `package` names the folder relative to the truth file. `frames`
    replaces `result.frames` as the source of the images (e.g. wrapped for a progress bar)."""
    out = Path(out_dir)
    tp = Path(truth_path) if truth_path is not None else out.with_name(out.name + ".truth.json")
    if tp.resolve().is_relative_to(out.resolve()):
        raise SynthError(f"truth path {tp} must not be inside the package {out}")
    rgb_frames = None if result.rgb is None else result.rgb.frames
    write_package(out, result.manifest, result.frames if frames is None else frames, rgb_frames)
    rel = os.path.relpath(out.resolve(), tp.resolve().parent)
    save_truth(replace(result.truth, package=rel), tp)
    return out


def load_buildings(truth: SynthTruth, model_path: str | os.PathLike[str] | None = None) -> list[Building]:
    """The buildings of a truth's scene: read from `model_path` (default: the truth's) or rebuilt
    with `procedural_block`; only the truth's `buildings` are kept, in that order."""
    if truth.procedural and model_path is None:
        blds = procedural_block(int(truth.procedural["n_buildings"]), int(truth.procedural["seed"]))
    else:
        path = model_path or truth.model_path
        if not path:
            raise SynthError("truth: no model_path and no procedural block to rebuild the buildings from")
        _, blds = read_model(path)
    index = {b.id: b for b in blds}
    missing = [i for i in truth.buildings if i not in index]
    if missing:
        raise SynthError(f"truth: building {missing[0]!r} is not in the model")
    return [index[i] for i in truth.buildings]
