"""Orientation bench: per-building coregistration of TIR frames on synthetic sequences.

Prints JSON with, per platform (`drive`, `flight`; synthetic sequences of `citytherm synth`):

1. the paper's table (Avbelj et al. 2012): efficiency (share of (frame, building) pairs whose
   refined projection fits the true one better than the prior) for constant initial position
   offsets dX = dY = dZ = +1 … +5 m and attitude offsets 0.5° … 3° (about each camera axis) added
   to the true poses; bars ≥ 0.95 at +5 m and at 2°;
2. the default GNSS/INS error model of `citytherm synth`: share of pairs with reprojection RMS of
   the building's edges (points every 0.5 m along its polygon edges that the true pose projects
   into the frame, occluded or not) below 1 px (bar ≥ 95 %), also for the pairs whose true view
   shows at least two model edges (hidden-edge removal), shares refined / prior, median position
   and rotation error of refined poses, feature and matching quality (completeness, correctness);
3. optionally (`--texture`) the texture accuracy of `citytherm run` with refinement on that
   sequence (written as CityGML and a sequence package) and on a drive around the bundled
   Berlin model (bars RMSE ≤ 0.45 K, misregistration ≤ 0.5 texel);
4. time per frame and building of the units' refinement (frames pre-rendered in memory),
   median; all of the orientation per (frame, building) pair: the sequence orientation (drives,
   once per frame) with the units, and with the calibration too (once per sequence on at most 40
   frames, so it weighs far more on these short sequences than on real ones);
5. for drives, the tie points of the sequence orientation against the truth (median error,
   share within 1 px).

The poses come from the stages `citytherm run` ships (`workers.job`: calibrate, orient when
the platform is close-range (calibration accepted or not), plan; then each unit's refinement,
`units.refine_unit`), on frames held in memory; only the pairs evaluated (frames whose true pose
sees the building) are the bench's own choice.

6. with `--quick` only the sequence orientation figures of `bench/orientation_sequence.py`: the
   calibrate and orient stages on a close-range sequence of one facade (priors 0.5 m / 1° off
   per frame plus a common error) and a drive with the default error model: frames below 1 px
   before / after, per-frame error median and 90th percentile, stage CPU and wall times.

7. with `--methods` only the orientation methods side by side (issue 19; `bench/orientation_methods.py`):
   per scene (drives with the default GNSS/INS errors, textured and homogeneous facades) and per
   `--orientation` (edges, sfm, both) frames oriented, (frame, building) pairs below 1 px,
   median px, the reconstruction's figures, and the bars (sfm ≥ 95 % of frames registered where
   edges reach < 80 %, ≥ 90 % of pairs below 1 px; both never worse than either alone).

Usage: `python bench/orientation.py [--frames 40] [--buildings 3] [--seed 1] [--texture] [--quick]
[--methods]`.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from workers import job
from workers.pipeline.geometry.citymodel import ModelHeader
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.manifest import MemoryFrames
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import pose_delta
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.building import CoregisterOptions
from workers.pipeline.orientation.quality import edge_points, tie_errors
from workers.pipeline.orientation.quality import reprojection_rms as quality_rms
from workers.pipeline.orientation.wireframe import building_wireframe, visible_wireframe
from workers.pipeline.plan import near_buildings
from workers.pipeline.synth import ErrorOptions, SynthOptions, procedural_block, synthesize
from workers.pipeline.units import UnitOptions, refine_unit, unit_raycaster


def reprojection_rms(camera, pts: np.ndarray, pose: Pose, truth: Pose) -> float:
    """RMS px of `pts` (seen in the frame by the true pose) projected with `pose` vs `truth`."""
    return quality_rms(camera, pts, pose, truth, min_points=4)


def offset_pose(pose: Pose, d_m: float, d_deg: float) -> Pose:
    """True pose moved by `d_m` along world x, y and z and rotated by `d_deg` about each camera axis."""
    from workers.pipeline.geometry.pose_increments import so3_exp

    R = pose.R_world_from_cam @ so3_exp(np.radians([d_deg, d_deg, d_deg]))
    return Pose(R, pose.center + d_m)


def scene(platform: str, frames: int, buildings: int, seed: int, errors: bool):
    res = synthesize(
        procedural_block(max(buildings + 3, 6), seed=seed),
        SynthOptions(
            platform=platform,
            n_frames=frames,
            seed=seed,
            buildings=buildings,
            errors=ErrorOptions(enabled=errors),
        ),
    )
    imgs = [res.frames.load(i) for i in range(frames)]
    return res, imgs


def ingested(res, imgs, priors: list[Pose], options: job.RunOptions) -> job.Ingested:
    """What the ingest stage gives for the synthetic sequence, with its frames in memory (so that
    timings measure orientation only) and `priors` in place of the manifest's."""
    m = res.manifest
    reach = min(options.plan.max_distance_m, options.unit.visibility.max_distance_m)
    near, _ = near_buildings(res.buildings, priors, reach)
    return job.Ingested(
        city_gml=Path("<synthetic>"),
        package_dir=Path("<memory>"),
        header=ModelHeader("2.0"),
        manifest=m,
        frames=MemoryFrames(imgs),
        priors=tuple(priors),
        buildings=tuple(near),
        n_model_buildings=len(res.buildings),
        radiometry=m.radiometry,
    )


def run(res, imgs, priors: list[Pose], options: CoregisterOptions) -> dict:
    """Calibrate the sequence and, where `citytherm run` does, orient it in blocks; plan the
    cluster's units and run their refinement; errors per pair (frames whose true pose sees the
    building's edges)."""
    cam = res.manifest.camera
    opts = job.RunOptions(unit=UnitOptions(refine=options), buildings=tuple(res.truth.cluster))
    ing = ingested(res, imgs, priors, opts)
    caster = job.scene_caster(ing)
    n = len(imgs)
    seconds = {"calibrate": 0.0, "orient": 0.0, "units": 0.0}
    t0 = time.perf_counter()
    calibrated = job.calibrate(ing, opts, caster)
    seconds["calibrate"] = time.perf_counter() - t0
    calib = {
        "run": True,
        **calibrated.calibration.to_dict(),
        "ms_per_frame": round(1000 * seconds["calibrate"] / n, 1),
    }
    t0 = time.perf_counter()
    oriented = job.orient(ing, calibrated, opts, caster=caster)
    seconds["orient"] = time.perf_counter() - t0
    orient = dict(oriented.report)
    caster = RayCaster(res.mesh)  # the whole rendered scene: the truth's visibility
    if oriented.orientation is not None:
        orient["ms_per_frame"] = round(1000 * seconds["orient"] / n, 1)
        orient["tie_points"] = tie_quality(oriented.orientation.tracks, cam, res.truth.poses, caster)
    planned = job.plan(ing, calibrated, oriented, opts)
    pairs, per_frame_ms = [], []
    for unit in planned.units:
        rc = unit_raycaster(unit)
        t0 = time.perf_counter()
        _, records = refine_unit(unit, rc)
        seconds["units"] += time.perf_counter() - t0
        per_frame_ms.append(1000 * (time.perf_counter() - t0) / len(unit.frames))
        records_of = {r.frame: r for r in records}
        pairs += evaluate(res, unit.building, records_of, priors, calibrated.priors, caster, options)
    return {
        "pairs": pairs,
        "per_frame_ms": per_frame_ms,
        "calibration": calib,
        "orientation": orient,
        "seconds": seconds,
    }


def evaluate(res, building, records: dict, original, calibrated, caster, options) -> list[dict]:
    """Per frame whose true pose sees the building's edge points (occluded or not): the
    reprojection RMS of its edges at the original prior, the calibrated prior and the unit's pose
    (a frame the plan did not give the unit: status "unplanned", at its calibrated prior), pose
    errors, and how many model edges the true view shows (hidden-edge removal)."""
    cam = res.manifest.camera
    pts = edge_points(building)
    wf = building_wireframe(building, options.edges)
    out = []
    for i, T in enumerate(res.truth.poses):
        if not np.isfinite(reprojection_rms(cam, pts, T, T)):
            continue
        r = records.get(i)
        pose, status = (r.pose, r.status) if r is not None else (calibrated[i], "unplanned")
        d = pose_delta(T, pose)
        out.append(
            {
                "before": reprojection_rms(cam, pts, original[i], T),
                "calibrated": reprojection_rms(cam, pts, calibrated[i], T),
                "after": reprojection_rms(cam, pts, pose, T),
                "status": status,
                "pos_err": float(np.linalg.norm(d[3:])),
                "rot_err_deg": float(np.degrees(np.linalg.norm(d[:3]))),
                "visible_edges": visible_wireframe(wf, cam, T, caster, options.edges).n_edges,
            }
        )
    return out


def tie_quality(tracks, camera, truth: list[Pose], caster: RayCaster) -> dict:
    """The tie points of the sequence orientation against the truth (`tie_errors`);
    correctness = share within 1 px."""
    e = tie_errors(tracks, camera, truth, caster)
    if not len(e):
        return {"observations": 0}
    per_frame = np.bincount(tracks.frame)
    return {
        "tracks": int(tracks.n_tracks),
        "observations": len(tracks.track),
        "median_error_px": round(float(np.median(e)), 3),
        "p90_error_px": round(float(np.percentile(e, 90)), 3),
        "correctness_1px": round(float(np.mean(e <= 1.0)), 3),
        "frames_with_8+_ties": int(np.sum(per_frame >= 8)),
        "frames": int(np.sum(per_frame > 0)),
    }


def _r(x, refined) -> float | None:
    return round(float(x), 3) if refined.any() else None


def summary(r: dict) -> dict:
    """Figures over the (frame, building) pairs the plan gives the units and whose true pose sees
    the building's edge points; the pairs the true pose sees but the plan did not give the
    building (its ray test found it hidden behind others) are counted apart."""
    p = [x for x in r["pairs"] if x["status"] != "unplanned"]
    unplanned = [x for x in r["pairs"] if x["status"] == "unplanned"]
    if not p:
        return {"pairs": 0, "pairs_not_planned": len(unplanned)}
    before = np.array([x["before"] for x in p])
    after = np.array([x["after"] for x in p])
    refined = np.array([x["status"] == "refined" for x in p])
    pos = np.array([x["pos_err"] for x in p])
    rot = np.array([x["rot_err_deg"] for x in p])
    out = {
        "pairs": len(p),
        "pairs_not_planned": len(unplanned),
        "pairs_not_planned_with_2+_visible_model_edges": sum(x["visible_edges"] >= 2 for x in unplanned),
        "efficiency": round(float(np.mean(after < before)), 3),
        "share_below_1px": round(float(np.mean(after < 1.0)), 3),
        "share_refined": round(float(np.mean(refined)), 3),
        "median_reprojection_px_prior": round(float(np.median(before)), 2),
        "median_reprojection_px_calibrated": round(float(np.median([x["calibrated"] for x in p])), 2),
        "median_reprojection_px_after": round(float(np.median(after)), 2),
        "refined_share_below_1px": _r(np.mean(after[refined] < 1.0), refined),
        "refined_worse_than_prior": int(np.sum(refined & (after > before))),
        "median_position_error_m_refined": _r(np.median(pos[refined]), refined),
        "median_rotation_error_deg_refined": _r(np.median(rot[refined]), refined),
        "median_position_error_m_all": round(float(np.median(pos)), 3),
        "median_rotation_error_deg_all": round(float(np.median(rot)), 3),
    }
    seen2 = np.array([x["visible_edges"] >= 2 for x in p])
    if seen2.any():
        out["pairs_with_2+_visible_model_edges"] = int(seen2.sum())
        out["share_below_1px_of_those"] = round(float(np.mean(after[seen2] < 1.0)), 3)
        out["efficiency_of_those"] = round(float(np.mean(after[seen2] < before[seen2])), 3)
    if r["per_frame_ms"]:
        out["ms_per_frame_and_building_median"] = round(float(np.median(r["per_frame_ms"])), 1)
        # all of the orientation per (frame, building) pair: the sequence orientation (once per
        # frame) with the units, and also with the calibration (once per sequence, on at most
        # 40 frames: on this short sequence it weighs 25 times what it does on 1,000 frames)
        sec = r["seconds"]
        out["orientation_ms_per_pair"] = round(1000 * (sec["orient"] + sec["units"]) / len(p), 1)
        out["orientation_with_calibration_ms_per_pair"] = round(1000 * sum(sec.values()) / len(p), 1)
    out["calibration"] = r["calibration"]
    out["sequence_orientation"] = r["orientation"]
    return out


def feature_quality(res, imgs, options: CoregisterOptions, n: int = 10) -> dict:
    """Completeness/correctness of feature extraction and matching against true corner positions,
    at the true pose (extraction) and after refinement from the prior (matching), tolerance 2 px."""
    from workers.pipeline.orientation.building import prior_information
    from workers.pipeline.orientation.frame_fit import fit_frame
    from workers.pipeline.orientation.quality import match_quality, point_quality

    cam = res.manifest.camera
    caster = RayCaster(res.mesh)
    priors = prior_poses(res.manifest, None)
    ext, mat = [], []
    for b in res.buildings:
        if b.id not in res.truth.cluster:
            continue
        wf = building_wireframe(b, options.edges)
        for i in range(0, len(imgs), max(len(imgs) // n, 1)):
            T = res.truth.poses[i]
            vis = visible_wireframe(wf, cam, T, caster, options.edges)
            if len(vis.corners) == 0:
                continue
            true_uv, _ = T.project(cam, vis.corner_points)
            info = prior_information(priors[i], res.manifest.accuracy, options)
            f = fit_frame(
                cam,
                wf,
                caster,
                imgs[i],
                priors[i],
                info,
                T,
                options.fit,
                options.edges,
                options.features,
                coarse=False,
            )
            pts = f.image_points
            if len(pts):
                near = np.min(np.linalg.norm(pts[:, None] - true_uv[None], axis=2), axis=1) < 30
                ext.append(point_quality(pts[near], true_uv, 2.0))
            idx = {int(c): k for k, c in enumerate(vis.corners)}
            m = [idx.get(int(c), -1) for c in f.corner_ids]
            keep = np.array([k >= 0 for k in m], bool)
            if len(m):
                mat.append(match_quality(np.array(m)[keep], f.corner_uv[keep], true_uv, 2.0))

    def mean(v, k):
        x = [t[k] for t in v if np.isfinite(t[k])]
        return round(float(np.mean(x)), 3) if x else None

    return {
        "extraction_completeness": mean(ext, 0),
        "extraction_correctness": mean(ext, 1),
        "matching_completeness": mean(mat, 0),
        "matching_correctness": mean(mat, 1),
        "frames_evaluated": len(ext),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--buildings", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--platforms", default="flight,drive")
    ap.add_argument("--texture", action="store_true", help="also run citytherm run on the sequences (slow)")
    ap.add_argument(
        "--texture-models",
        default="procedural,berlin",
        help="scenes of the texture runs: procedural (the scene above), berlin (bundled model)",
    )
    ap.add_argument(
        "--quick",
        action="store_true",
        help="only the sequence orientation figures (bench/orientation_sequence.py --quick)",
    )
    ap.add_argument("--methods", action="store_true", help="only edges / sfm / both side by side")
    a = ap.parse_args()
    if a.methods:
        from bench.orientation_methods import method_figures

        t0 = time.perf_counter()
        scenes = ["textured", "homogeneous"]
        res = {"bench": "orientation", "methods": method_figures(a.frames, a.seed, scenes)}
        res["wall_s"] = round(time.perf_counter() - t0, 1)
        print(json.dumps(res, indent=1))
        return
    if a.quick:
        from bench.orientation_sequence import sequence_figures

        t0 = time.perf_counter()
        quick = {"bench": "orientation", "quick": True, **sequence_figures(a.frames, 3, quick=True)}
        quick["wall_s"] = round(time.perf_counter() - t0, 1)
        print(json.dumps(quick, indent=1))
        return
    options = CoregisterOptions()
    out: dict = {"bench": "orientation", "frames": a.frames, "cluster_buildings": a.buildings, "seed": a.seed}
    t_all = time.perf_counter()
    for platform in a.platforms.split(","):
        sec: dict = {}
        res0, imgs0 = scene(platform, a.frames, a.buildings, a.seed, errors=False)
        table = {}
        for d_m in (1, 2, 3, 4, 5):
            pri = [offset_pose(p, d_m, 0.0) for p in res0.truth.poses]
            table[f"dXYZ=+{d_m}m"] = summary(run(res0, imgs0, pri, options))
        for d_deg in (0.5, 1.0, 2.0, 3.0):
            pri = [offset_pose(p, 0.0, d_deg) for p in res0.truth.poses]
            table[f"attitude={d_deg}deg"] = summary(run(res0, imgs0, pri, options))
        sec["paper_table_efficiency"] = {k: v.get("efficiency") for k, v in table.items()}
        sec["paper_table"] = table
        res, imgs = scene(platform, a.frames, a.buildings, a.seed, errors=True)
        pri = prior_poses(res.manifest, None)
        r = run(res, imgs, pri, options)
        sec["default_error_model"] = summary(r)
        sec["feature_quality"] = feature_quality(res, imgs, options)
        e = table
        sec["bars"] = {
            "efficiency_at_5m>=0.95": (e["dXYZ=+5m"].get("efficiency") or 0) >= 0.95,
            "efficiency_at_2deg>=0.95": (e["attitude=2.0deg"].get("efficiency") or 0) >= 0.95,
            "share_below_1px>=0.95": (sec["default_error_model"].get("share_below_1px") or 0) >= 0.95,
            "median_ms<=30": (sec["default_error_model"].get("ms_per_frame_and_building_median") or 1e9)
            <= 30,
            "orientation_ms_per_pair<=30": (sec["default_error_model"].get("orientation_ms_per_pair") or 1e9)
            <= 30,
        }
        out[platform] = sec
        if a.texture:
            out.setdefault("texture", {})[platform] = [
                texture_run(platform, a.frames, a.buildings, a.seed, m) for m in a.texture_models.split(",")
            ]
    if "texture" not in out:
        out["texture"] = "not run (pass --texture; needs `citytherm run` with refinement)"
    out["wall_s"] = round(time.perf_counter() - t_all, 1)
    print(json.dumps(out, indent=1))


def texture_run(platform: str, frames: int, buildings: int, seed: int, model: str) -> dict:
    """`citytherm run` with refinement on a synthetic sequence with the default error model:
    `model` "procedural" is the scene of the orientation figures above (the procedural block,
    written as CityGML), "berlin" a drive around the bundled real model. Texture accuracy and
    orientation figures against the truth, and the same run without refinement for comparison."""
    from db.citygml.reader import read_model
    from db.citygml.writer import write_citygml
    from db.synth_files import write_synthetic_package
    from workers.pipeline.synth import BUNDLED_MODEL
    from workers.run import run_job
    from workers.synth_eval import orientation_accuracy, texture_accuracy

    root = Path(tempfile.mkdtemp(prefix="citytherm-bench-orientation-"))
    if model == "berlin":
        gml, blds = BUNDLED_MODEL, read_model(BUNDLED_MODEL)[1]
    else:
        blds = procedural_block(max(buildings + 3, 6), seed=seed)
        gml = root / "procedural.gml"
        write_citygml(gml, blds, srs_name=blds[0].srs_name)
    opts = SynthOptions(
        platform=platform, n_frames=frames, seed=seed, buildings=buildings, model_path=str(gml)
    )
    res = synthesize(blds, opts)
    pkg = write_synthetic_package(res, root / "seq")
    # texels per metre: 10 for drives (about 1.5 cm per pixel at 11 m), 2.5 for flights (about
    # 0.35 m per pixel at 200 m: finer texels would get no observation)
    resolution = 10.0 if platform == "drive" else 2.5
    out: dict = {"model": model, "resolution_px_per_m": resolution}
    for refine in (True, False):
        dest = root / ("refined" if refine else "prior")
        t0 = time.perf_counter()
        options = job.RunOptions.build(resolution_px_per_m=resolution, refine=refine, display=False)
        run_job(gml, pkg, dest, options)
        wall = time.perf_counter() - t0
        acc = texture_accuracy(dest, res)
        acc.update(orientation_accuracy(dest, res))
        r = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in acc.items()}
        r["run_wall_s"] = round(wall, 1)
        if refine:
            rep = json.loads((dest / "report.json").read_text())
            r["calibration_accepted"] = rep["calibration"].get("accepted")
            so = rep.get("sequence_orientation", {})
            r["sequence_orientation"] = {k: so.get(k) for k in ("run", "frames", "frames_oriented")}
            r["stage_s"] = {k: round(v, 2) for k, v in rep["timings_s"].items()}
        out["refine" if refine else "no_refine"] = r
    ref = out["refine"]
    out["bars"] = {
        "rmse_k<=0.45": ref["rmse_k"] <= 0.45,
        "misregistration<=0.5": (ref.get("misregistration_median_texel") or 1e9) <= 0.5,
    }
    out["results"] = str(root)
    return out


if __name__ == "__main__":
    main()
