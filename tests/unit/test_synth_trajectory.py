"""Drive and flight trajectories: distances, speed, heading, camera direction."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from workers.pipeline.geometry.georef import camera_pose
from workers.pipeline.geometry.manifest import Mounting
from workers.pipeline.synth import DriveOptions, FlightOptions, PathTrajectory, SynthError, procedural_block
from workers.pipeline.synth.shapes import footprint
from workers.pipeline.synth.trajectory import (
    camera_to_body,
    choose_cluster,
    drive_loop,
    flight_loop,
    ground_height,
)


@pytest.fixture(scope="module")
def block():
    return procedural_block(15, seed=4)


def test_drive_stays_outside_footprints_at_street_distance(block):
    cluster = choose_cluster(block, 4, seed=1)
    loop, members = drive_loop(block, cluster, DriveOptions())
    assert set(cluster) <= set(members)
    ring = shapely.LinearRing(loop)
    cluster_shape = shapely.union_all([footprint(block[i]) for i in members])
    assert ring.distance(cluster_shape) >= 8.0 - 0.05
    d = shapely.distance(cluster_shape, shapely.points(loop))
    assert np.median(d) < 15.0
    for b in block:
        assert ring.distance(footprint(b)) > 1.0  # never enters any footprint
    assert not shapely.LinearRing(loop).is_ccw  # clockwise: buildings on the right


def test_drive_motion_heading_and_camera(block):
    cluster = choose_cluster(block, 3, seed=2)
    loop, members = drive_loop(block, cluster, DriveOptions())
    gz = ground_height(block)
    traj = PathTrajectory(loop, gz + 2.25, 8.0, start_m=17.0, t0=10.0, sway_deg=0.3, seed=3)
    t = 10.0 + 0.1 * np.arange(200)
    P, A = traj.state(t)
    step = np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1)
    assert np.allclose(step / 0.1, 8.0, rtol=0.02)  # 8 m/s (chords of the rounded corners)
    assert np.allclose(P[:, 2], gz + 2.25)
    motion = np.degrees(np.arctan2(np.diff(P[:, 0]), np.diff(P[:, 1])))
    mid_heading = A[:-1, 2] + 0.5 * ((A[1:, 2] - A[:-1, 2] + 180) % 360 - 180)
    assert np.max(np.abs((motion - mid_heading + 180) % 360 - 180)) < 3.0  # heading along the path
    assert np.all(np.abs(A[:, :2]) <= 0.3 * 2 + 1e-9)
    # the camera looks right, forward and up: its axis points toward the buildings
    M = camera_to_body(25.0, 12.0)
    cluster_shape = shapely.union_all([footprint(block[i]) for i in members])
    toward = 0
    for k in range(0, 200, 10):
        pose = camera_pose(P[k], A[k], Mounting(M))
        z = pose.R_world_from_cam[:, 2]
        assert 8.0 < np.degrees(np.arcsin(z[2])) < 16.0  # tilted up ~12°
        ray = shapely.LineString([pose.center[:2], pose.center[:2] + 40 * z[:2] / np.linalg.norm(z[:2])])
        toward += ray.intersects(cluster_shape)
    assert toward >= 12  # most of the time (not while rounding a corner)


def test_flight_circle_looks_45_down_at_cluster(block):
    cluster = choose_cluster(block, 5, seed=1)
    o = FlightOptions(height_m=200.0, speed_mps=20.0)
    loop = flight_loop(block, cluster, o)
    gz = ground_height(block)
    traj = PathTrajectory(loop, gz + 200.0, 20.0, bank=True, seed=1)
    M = camera_to_body(0.0, -(45.0 - traj.mean_bank_deg))
    centre = np.asarray(shapely.union_all([footprint(block[i]) for i in cluster]).centroid.coords[0])
    P, A = traj.state(np.arange(0, 30, 1.0))
    assert 5.0 < traj.mean_bank_deg < 20.0  # coordinated turn at 20 m/s on a 200 m circle
    for k in range(len(P)):
        pose = camera_pose(P[k], A[k], Mounting(M))
        z = pose.R_world_from_cam[:, 2]
        assert abs(np.degrees(np.arcsin(-z[2])) - 45.0) < 1.5
        hit = pose.center + z * (pose.center[2] - gz) / -z[2]  # where the axis meets the ground
        assert np.linalg.norm(hit[:2] - centre) < 15.0


def test_flight_strips_and_bad_pattern(block):
    cluster = choose_cluster(block, 5, seed=1)
    loop = flight_loop(block, cluster, FlightOptions(pattern="strips", height_m=150.0))
    assert len(loop) > 100 and not shapely.LinearRing(loop).is_ccw
    with pytest.raises(SynthError, match="pattern"):
        flight_loop(block, cluster, FlightOptions(pattern="spiral"))  # type: ignore[arg-type]


def test_cluster_choice(block):
    ids = [block[3].id, block[4].id]
    assert choose_cluster(block, ids) == [3, 4]
    assert len(choose_cluster(block, 6, seed=9)) == 6
    with pytest.raises(SynthError, match="unknown building"):
        choose_cluster(block, ["nope"])


def test_procedural_houses_are_closed_and_outward(block):
    from workers.pipeline.geometry.polygons import fit_plane, newell_normal

    for b in block[:5]:
        lo, hi = b.bounds()
        centre = 0.5 * (lo + hi)
        area = np.zeros(3)
        for poly in b.polygons:
            plane = fit_plane(poly)
            assert plane.max_deviation < 1e-9
            assert plane.normal @ (plane.centroid - centre) > 0  # normals point out of the house
            area += newell_normal(poly.exterior.coords)
        assert np.abs(area).max() < 1e-6  # a closed surface: area vectors cancel


def test_trajectory_laps_repeat(block):
    loop, _ = drive_loop(block, choose_cluster(block, 2, seed=3), DriveOptions())
    traj = PathTrajectory(loop, 2.0, 8.0, start_m=5.0, t0=0.0)
    lap = traj.length / 8.0
    t = np.array([0.3, 7.1, 12.9])
    P0, A0 = traj.state(t)
    P1, A1 = traj.state(t + 3 * lap)
    assert np.allclose(P0, P1, atol=1e-6)
    assert np.allclose((A1[:, 2] - A0[:, 2] + 180) % 360 - 180, 0.0, atol=1e-6)
    assert np.all((A0[:, 2] >= 0) & (A0[:, 2] < 360))
