"""The coregistered block's similarity corrected by the model edges (`reconstruction.edge_placement`):
a drive along one homogeneous wall, the block placed 0.5 m too low (32 px), 0.2 m along the wall, turned
0.3° about the wall's normal and scaled by 1 %: the eave, the ground line and the corner bring it
back where the facade plane cannot."""

from __future__ import annotations

import numpy as np

from tests.unit.orientation_scenes import CAMERA, Renderer, box_building, drive_poses
from workers.pipeline.orientation.wireframe import mesh_wireframe
from workers.pipeline.reconstruction.edge_placement import fit_on_edges
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.reconstruction.similarity import similarity_about


def test_edges_fix_what_one_facade_leaves_open() -> None:
    scene = Renderer([box_building("B", 0.0, 0.0, 20.0, 10.0, 8.0)], windows=False)
    truth = drive_poses(np.array([23.0, -12.0, 1.5]), np.array([-1.0, 0.0, 0.0]), 8, step_m=1.2, up_deg=15.0)
    images = {k: scene.render(p, k) for k, p in enumerate(truth)}
    pivot = np.mean([p.center for p in truth], axis=0)
    # what the south wall (normal −y) leaves open: shift along x and z, turn about y, scale
    off = similarity_about(np.r_[np.radians([0.0, 0.3, 0.0]), [0.2, 0.0, -0.5], np.log(1.01)], pivot)
    placed = off.poses(dict(enumerate(truth)))
    sig = np.r_[np.radians([0.01, 1.0, 0.01]), [1.0, 0.01, 1.0], 0.05]  # the planes fixed y and two tilts
    wf = mesh_wireframe(scene.mesh)
    ep = fit_on_edges(
        CAMERA, scene.caster, wf, placed, images, pivot, np.diag(sig**-2.0), ReconstructionOptions()
    )
    assert ep is not None and ep.kept and ep.support_after > ep.support_before + 0.3
    back = ep.correction.poses(placed)
    err = np.array([np.linalg.norm(back[k].center - p.center) for k, p in enumerate(truth)])
    before = np.array([np.linalg.norm(placed[k].center - p.center) for k, p in enumerate(truth)])
    assert before.min() > 0.2
    assert err.max() < 0.03, err


def test_a_sub_pixel_height_error_is_corrected() -> None:
    """A block 1.2 cm low (0.4 px: the support, samples within 1.5 px of an edge, falls from
    0.889 to 0.885 when it is corrected) is brought back: the edges' mean offset (0.38 ->
    0.08 px) tells the correction is better."""
    scene = Renderer([box_building("B", 0.0, 0.0, 20.0, 10.0, 8.0)], windows=False)
    truth = drive_poses(np.array([23.0, -12.0, 1.5]), np.array([-1.0, 0.0, 0.0]), 8, step_m=1.2, up_deg=15.0)
    images = {k: scene.render(p, k) for k, p in enumerate(truth)}
    pivot = np.mean([p.center for p in truth], axis=0)
    low = similarity_about(np.r_[np.zeros(3), [0.0, 0.0, -0.012], 0.0], pivot)
    placed = low.poses(dict(enumerate(truth)))
    sig = np.r_[np.radians([0.01, 0.01, 0.01]), [0.01, 0.01, 1.0], 0.001]  # the height open
    ep = fit_on_edges(
        CAMERA, scene.caster, mesh_wireframe(scene.mesh), placed, images, pivot, np.diag(sig**-2.0),
        ReconstructionOptions(),
    )  # fmt: skip
    assert ep is not None and ep.kept, ep and ep.to_dict()
    assert ep.offset_after_px < 0.9 * ep.offset_before_px
    back = ep.correction.poses(placed)
    err = np.array([abs(back[k].center[2] - p.center[2]) for k, p in enumerate(truth)])
    assert err.max() < 0.003, err
