"""Cases for measuring the product against the reference texturer (bench and tests share them).

In: a `CaseSpec` (which real LoD2 file, drive or flight, how many frames, true or erroneous
poses). Out: a `Case` (the `SynthResult` over the whole file, so that the neighbours occlude, and
its sequence package on disk), the product's results folder made through the shipped path
(`workers.run.run_job`, exactly what `citytherm run` does) as a `ProductRun`, and the reference's
textures from the true poses and the package's frames (`run_reference`). The figures are
`tests.reference.evaluate.compare_case`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from tests.reference.geometry import ScenePolygon, scene_polygons
from tests.reference.texturer import ReferenceOptions, RefTexture, reference_textures
from tests.reference.zbuffer import RefCamera, RefGround

REPO = Path(__file__).resolve().parents[2]

#: the real CityGML files the cases are laid over
SCENES: dict[str, Path] = {
    "nrw": REPO / "tests" / "data" / "nrw-tile-5659-citygml1-lod2.gml",
    "berlin": REPO / "workers" / "pipeline" / "synth" / "data" / "berlin-61-buildings-citygml1-lod2.gml",
    "potsdam": REPO / "tests" / "data" / "potsdam-97-buildings-citygml1-lod1.gml",
}


@dataclass(frozen=True)
class CaseSpec:
    """One synthetic sequence over a real model.

    Attributes:
        scene: key of `SCENES`.
        platform: `drive` (car, facades) or `flight` (helicopter, oblique).
        n_frames: frames of the sequence.
        errors: False: error-free poses (the package's priors are the true poses); True: the
            synthetic generator's default GNSS/INS errors.
        seed: seed of the scene (cluster, textures, trajectory, noise).
        cluster: buildings of the cluster the path goes round.
        frame_interval_s: seconds between frames (None: 0.1 s for drives, 0.5 s for flights, so
            a short flight still turns through a useful arc).
        ref_texels_per_m: the reference's grid density (None: 10 for drives, 4 for flights, about
            one texel per pixel of a 200 m flight; the figures are per texel, so the reference's
            own density only sets its cost).
    """

    scene: str
    platform: Literal["drive", "flight"]
    n_frames: int
    errors: bool = False
    seed: int = 1
    cluster: int = 4
    frame_interval_s: float | None = None
    ref_texels_per_m: float | None = None

    @property
    def name(self) -> str:
        """`<scene>-<platform>[-errors]`."""
        return f"{self.scene}-{self.platform}" + ("-errors" if self.errors else "")


@dataclass(frozen=True, eq=False)
class Case:
    """A case made on disk: `res` (the `SynthResult`), `package` (its folder), `model` (the
    CityGML file the product reads)."""

    spec: CaseSpec
    res: Any  # workers.pipeline.synth.SynthResult
    package: Path
    model: Path
    synth_s: float


def make_case(spec: CaseSpec, root: Path) -> Case:
    """Synthesize `spec` over its whole model and write the package under `root/<name>/seq`
    (frames rendered here, once; the reference reads the same files as the product)."""
    from db.citygml.reader import read_model
    from db.synth_files import write_synthetic_package
    from workers.pipeline.synth import ErrorOptions, SynthOptions, synthesize

    t0 = time.perf_counter()
    model = SCENES[spec.scene]
    _, buildings = read_model(model)
    interval = spec.frame_interval_s or (0.1 if spec.platform == "drive" else 0.5)
    res = synthesize(
        buildings,
        SynthOptions(
            platform=spec.platform,
            n_frames=spec.n_frames,
            seed=spec.seed,
            buildings=spec.cluster,
            frame_interval_s=interval,
            errors=ErrorOptions() if spec.errors else ErrorOptions(enabled=False),
            model_path=str(model),
        ),
    )
    pkg = write_synthetic_package(res, root / spec.name / "seq")
    return Case(spec, res, pkg, model, time.perf_counter() - t0)


@dataclass(frozen=True)
class ProductRun:
    """The product's results folder and its figures: `report` (report.json), `wall_s` of
    `run_job`, `pairs` (building-frame pairs textured), texture-stage seconds and frames/s."""

    out_dir: Path
    report: dict[str, Any]
    wall_s: float
    pairs: int
    texture_stage_s: float
    frames_per_s: float | None


def run_product(
    case: Case, out_dir: Path, refine: bool, workers: int = 1, options: dict[str, Any] | None = None
) -> ProductRun:
    """`citytherm run <model> <package> -o out_dir [--no-refine] --no-display` through
    `workers.run.run_job` (the shipped path, default options otherwise). The texture-stage speed
    is the units' `decode + texture` time per building-frame pair (as `bench/texture.py` always
    measured it: frames/s per worker process). `options`: overrides of the job's options
    (`RunOptions.to_dict` form, nested; e.g. `{"unit": {"visibility": {"blur_margin_px": 2}}}`)."""
    from workers.job import RunOptions
    from workers.run import run_job

    t0 = time.perf_counter()
    opts = RunOptions.build(refine=refine, workers=workers, display=False)
    if options:
        opts = RunOptions.from_dict(_merged(opts.to_dict(), options))
    summary = run_job(case.model, case.package, out_dir, opts)
    wall = time.perf_counter() - t0
    report = json.loads((out_dir / "report.json").read_text(encoding="utf-8"))
    st = report.get("unit_stage_timings_s", {})
    tex_s = float(st.get("decode", 0.0)) + float(st.get("texture", 0.0))
    pairs = int(sum(summary.units_frames.values()))
    return ProductRun(out_dir, report, wall, pairs, tex_s, pairs / tex_s if tex_s else None)


def _merged(base: dict[str, Any], patch: dict[str, Any]) -> dict[str, Any]:
    """`base` with `patch` merged in, nested dictionaries key by key."""
    out = dict(base)
    for k, v in patch.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def frame_loader(case: Case) -> Any:
    """`index -> (H, W) float32 kelvin` reading the package's frame files (`cv2.imread`, then
    the manifest's `DN · scale + offset`): the very pixels the product reads."""
    rad = case.res.manifest.radiometry
    files = [case.package / f.file for f in case.res.manifest.frames]
    scale, offset = float(rad.scale), float(rad.offset)

    def load(i: int) -> np.ndarray:
        dn = cv2.imread(str(files[i]), cv2.IMREAD_UNCHANGED)
        if dn is None:
            raise FileNotFoundError(files[i])
        return (dn.astype(np.float32) * np.float32(scale) + np.float32(offset)).astype(np.float32)

    return load


def reference_options(spec: CaseSpec) -> ReferenceOptions:
    """The reference's options for a case (grid density by platform, see `CaseSpec`)."""
    tpm = spec.ref_texels_per_m or (10.0 if spec.platform == "drive" else 4.0)
    return ReferenceOptions(texels_per_m=tpm)


def run_reference(
    case: Case, options: ReferenceOptions | None = None
) -> tuple[list[ScenePolygon], dict[str, RefTexture], float]:
    """The reference's textures of every polygon of the rendered scene, from the TRUE poses
    (`res.truth.poses`) and the package's frames; returns (scene polygons, textures by polygon
    id, seconds)."""
    t0 = time.perf_counter()
    res = case.res
    polys = scene_polygons(res.buildings)
    poses = [(p.R_world_from_cam, p.center) for p in res.truth.poses]
    o = options or reference_options(case.spec)
    tex = reference_textures(
        polys,
        None,
        RefCamera.from_params(res.manifest.camera, supersample=o.supersample),
        poses,
        frame_loader(case),
        o,
        ground_z=RefGround.from_truth(res.truth),
    )
    return polys, tex, time.perf_counter() - t0
