"""The scene wireframe the calibrate and orient stages of one process share
(`workers.job.scene_wireframe`): made once per ray caster and edge options, equal to
`mesh_wireframe` of the caster's mesh."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from workers import job
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.orientation.wireframe import EdgeOptions, mesh_wireframe
from workers.pipeline.synth import procedural_block


def test_one_wireframe_per_caster_and_options_equal_to_the_meshs() -> None:
    caster = RayCaster(build_scene_mesh(procedural_block(3, seed=1)))
    edges = EdgeOptions()
    wf = job.scene_wireframe(caster, edges)
    assert wf is not None
    made = mesh_wireframe(caster.mesh, edges)
    assert np.array_equal(wf.vertices, made.vertices) and np.array_equal(wf.edges, made.edges)
    assert job.scene_wireframe(caster, EdgeOptions()) is wf  # equal options: the same object
    coarser = job.scene_wireframe(caster, replace(edges, crease_angle_deg=30.0))
    assert coarser is not None and coarser is not wf
    other = RayCaster(build_scene_mesh(procedural_block(3, seed=1)))  # another caster: made anew
    assert job.scene_wireframe(other, edges) is not wf


def test_a_scene_without_triangles_has_no_wireframe() -> None:
    assert job.scene_wireframe(RayCaster(build_scene_mesh([])), EdgeOptions()) is None
