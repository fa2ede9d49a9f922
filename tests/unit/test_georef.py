"""Direct georeferencing: hand-worked poses, rotation properties, time interpolation, CRS."""

from __future__ import annotations

import numpy as np
import pyproj
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.georef import (
    R_WORLD_FROM_NED,
    GeorefError,
    Rx,
    Ry,
    Rz,
    Trajectory,
    attitude_from_ned_from_body,
    body_from_cam,
    camera_pose,
    camera_pose_arrays,
    camera_poses,
    ins_from_camera,
    meridian_convergence_deg,
    model_positions,
    ned_from_body,
    prior_poses,
    world_trajectory,
)
from workers.pipeline.geometry.manifest import FrameRecord, ImuSamples, Mounting, Radiometry, SequenceManifest

FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # spec's forward camera
CAM = Camera(640, 512, 880.0, 880.0, 319.5, 255.5)
EAST, NORTH, UP = np.eye(3)


def mounting(boresight=(0.0, 0.0, 0.0), lever=(0.0, 0.0, 0.0), M=FORWARD) -> Mounting:
    return Mounting(np.asarray(M, float), np.asarray(boresight, float), np.asarray(lever, float))


def axes(pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World directions of the camera's x (right), y (down), z (optical axis)."""
    R = pose.R_world_from_cam
    return R[:, 0], R[:, 1], R[:, 2]


def manifest(
    positions,
    attitudes,
    times=None,
    crs="EPSG:25832",
    heading_reference="grid",
    vertical_offset_m=0.0,
    imu=None,
    mnt=None,
) -> SequenceManifest:
    positions = np.asarray(positions, float).reshape(-1, 3)
    attitudes = np.asarray(attitudes, float).reshape(-1, 3)
    times = np.arange(len(positions), dtype=float) if times is None else np.asarray(times, float)
    frames = tuple(
        FrameRecord(i, f"frames/{i:06d}.png", float(times[i]), positions[i], attitudes[i])
        for i in range(len(positions))
    )
    return SequenceManifest(
        platform="drive",
        crs=crs,
        camera=CAM,
        radiometry=Radiometry(),
        mounting=mnt or mounting(),
        frames=frames,
        heading_reference=heading_reference,
        vertical_offset_m=vertical_offset_m,
        imu=imu,
    )


# -- elementary rotations and hand-worked poses ---------------------------------------------------
def test_elementary_rotations_match_spec_matrices() -> None:
    a = 0.3
    c, s = np.cos(a), np.sin(a)
    np.testing.assert_allclose(Rx(a), [[1, 0, 0], [0, c, -s], [0, s, c]])
    np.testing.assert_allclose(Ry(a), [[c, 0, s], [0, 1, 0], [-s, 0, c]])
    np.testing.assert_allclose(Rz(a), [[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_array_equal(R_WORLD_FROM_NED, [[0, 1, 0], [1, 0, 0], [0, 0, -1]])
    assert Rz(np.array([0.1, 0.2, 0.3])).shape == (3, 3, 3)


def test_level_camera_heading_0_looks_north_heading_90_looks_east() -> None:
    x, y, z = axes(camera_pose([0, 0, 0], [0, 0, 0], mounting()))
    np.testing.assert_allclose(z, NORTH, atol=1e-12)
    np.testing.assert_allclose(x, EAST, atol=1e-12)  # image right = east
    np.testing.assert_allclose(y, -UP, atol=1e-12)  # image down = down
    x, y, z = axes(camera_pose([0, 0, 0], [0, 0, 90], mounting()))
    np.testing.assert_allclose(z, EAST, atol=1e-12)
    np.testing.assert_allclose(x, -NORTH, atol=1e-12)  # image right = south
    np.testing.assert_allclose(y, -UP, atol=1e-12)


def test_point_ahead_projects_to_principal_point() -> None:
    P = np.array([691000.0, 5334000.0, 520.0])
    pose = camera_pose(P, [0, 0, 90], mounting())
    uv, depth = pose.project(CAM, (P + np.array([25.0, 0, 0]))[None])
    np.testing.assert_allclose(uv, [[319.5, 255.5]], atol=1e-9)
    np.testing.assert_allclose(depth, [25.0])
    # a point higher up appears higher in the image (smaller v), one to the south to the right
    uv, _ = pose.project(CAM, np.array([P + np.array([25.0, 0, 1.0]), P + np.array([25.0, -1.0, 0])]))
    assert uv[0, 1] < 255.5 and abs(uv[0, 0] - 319.5) < 1e-9
    assert uv[1, 0] > 319.5 and abs(uv[1, 1] - 255.5) < 1e-9


def test_roll_90_turns_image_down_to_the_left() -> None:
    # right wing down by 90°, heading north: body y (right) points down, body z (down) west
    x, y, z = axes(camera_pose([0, 0, 0], [90, 0, 0], mounting()))
    np.testing.assert_allclose(z, NORTH, atol=1e-12)
    np.testing.assert_allclose(x, -UP, atol=1e-12)
    np.testing.assert_allclose(y, -EAST, atol=1e-12)


def test_pitch_up_raises_the_optical_axis() -> None:
    _, _, z = axes(camera_pose([0, 0, 0], [0, 10, 0], mounting()))
    np.testing.assert_allclose(z, [0, np.cos(np.radians(10)), np.sin(np.radians(10))], atol=1e-12)


def test_lever_arm_along_body_x_moves_centre_forward() -> None:
    P = np.array([100.0, 200.0, 30.0])
    pose = camera_pose(P, [0, 0, 0], mounting(lever=(1.5, 0, 0)))
    np.testing.assert_allclose(pose.center, P + np.array([0, 1.5, 0]), atol=1e-12)  # north
    pose = camera_pose(P, [0, 0, 90], mounting(lever=(1.5, 0, 0)))
    np.testing.assert_allclose(pose.center, P + np.array([1.5, 0, 0]), atol=1e-12)  # east
    pose = camera_pose(P, [0, 0, 0], mounting(lever=(0, 0, 2.0)))  # body z = down
    np.testing.assert_allclose(pose.center, P + np.array([0, 0, -2.0]), atol=1e-12)


def test_boresight_composition_order() -> None:
    # bx = 90 first (camera right -> body down), then bz = 90 (optical axis forward -> right)
    R = body_from_cam(mounting(boresight=(90, 0, 90)))
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 1, 0], atol=1e-12)  # optical axis = body right
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 0, 1], atol=1e-12)  # image right = body down
    # the other order (Rx after Rz) would look down: make sure we do not
    assert not np.allclose(R, Rx(np.pi / 2) @ Rz(np.pi / 2) @ FORWARD)
    # at heading 0 the camera then looks east with image right pointing down
    x, _, z = axes(camera_pose([0, 0, 0], [0, 0, 0], mounting(boresight=(90, 0, 90))))
    np.testing.assert_allclose(z, EAST, atol=1e-12)
    np.testing.assert_allclose(x, -UP, atol=1e-12)


def test_large_boresight_is_exact_not_linearised() -> None:
    # 8° pitch misalignment: the optical axis is exactly 8° above the horizon
    _, _, z = axes(camera_pose([0, 0, 0], [0, 0, 0], mounting(boresight=(0, 8, 0))))
    np.testing.assert_allclose(np.degrees(np.arcsin(z[2])), 8.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(z), 1.0, atol=1e-15)


def test_nadir_mounting() -> None:
    # camera looking straight down (camera z = body z), image top towards the nose
    M = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    _, y, z = axes(camera_pose([0, 0, 0], [0, 0, 90], mounting(M=M)))
    np.testing.assert_allclose(z, -UP, atol=1e-12)
    np.testing.assert_allclose(y, -EAST, atol=1e-12)  # image down = backwards


# -- properties -----------------------------------------------------------------------------------
angles = st.tuples(st.floats(-180, 180), st.floats(-89.5, 89.5), st.floats(0, 360, exclude_max=True))


@settings(max_examples=150, deadline=None, derandomize=True)
@given(att=angles, bore=st.tuples(*[st.floats(-15, 15)] * 3))
def test_rotations_stay_orthonormal(att, bore) -> None:
    R = ned_from_body(att)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(R) - 1) < 1e-12
    pose = camera_pose([1.0, 2.0, 3.0], att, mounting(boresight=bore, lever=(0.3, -0.2, 1.0)))
    Rwc = pose.R_world_from_cam
    np.testing.assert_allclose(Rwc.T @ Rwc, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(Rwc) - 1) < 1e-12
    # the lever arm keeps its length
    np.testing.assert_allclose(np.linalg.norm(pose.center - [1, 2, 3]), np.linalg.norm([0.3, -0.2, 1.0]))


@settings(max_examples=150, deadline=None, derandomize=True)
@given(att=angles)
def test_attitude_round_trip(att) -> None:
    back = attitude_from_ned_from_body(ned_from_body(att))
    np.testing.assert_allclose(ned_from_body(back), ned_from_body(att), atol=1e-12)
    assert 0 <= back[2] < 360
    if abs(att[1]) < 89:
        d = (back - np.array(att) + 180) % 360 - 180
        np.testing.assert_allclose(d, 0, atol=1e-8)


def test_vectorised_poses_equal_single_poses() -> None:
    rng = np.random.default_rng(3)
    P = rng.normal(size=(20, 3)) * 100
    A = rng.uniform([-30, -30, 0], [30, 30, 360], (20, 3))
    g = rng.uniform(-2, 2, 20)
    m = mounting(boresight=(1, -2, 3), lever=(0.5, 0.1, -1))
    many = camera_poses(P, A, m, g)
    for i in range(20):
        one = camera_pose(P[i], A[i], m, g[i])
        np.testing.assert_allclose(many[i].R_world_from_cam, one.R_world_from_cam, atol=1e-15)
        np.testing.assert_allclose(many[i].center, one.center, atol=1e-12)
    assert ned_from_body(A).shape == (20, 3, 3)


@settings(max_examples=100, deadline=None, derandomize=True)
@given(att=angles, bore=st.tuples(*[st.floats(-10, 10)] * 3), gamma=st.floats(-3, 3))
def test_ins_from_camera_inverts_camera_pose(att, bore, gamma) -> None:
    m = mounting(boresight=bore, lever=(0.4, -0.3, -1.2))
    P = np.array([691000.0, 5334000.0, 520.0])
    pose = camera_pose(P, att, m, gamma)
    P2, att2 = ins_from_camera(pose, m, gamma)
    np.testing.assert_allclose(P2, P, atol=1e-8)
    np.testing.assert_allclose(ned_from_body(att2), ned_from_body(att), atol=1e-12)
    R, C = camera_pose_arrays(P[None], np.array(att)[None], m, gamma)
    np.testing.assert_allclose(R[0], pose.R_world_from_cam, atol=1e-15)
    np.testing.assert_allclose(C[0], pose.center, atol=1e-9)


times_st = st.lists(st.floats(0.01, 5.0), min_size=2, max_size=12).map(lambda d: np.cumsum(d) - 1.0)


@settings(max_examples=80, deadline=None, derandomize=True)
@given(t=times_st, seed=st.integers(0, 10_000))
def test_interpolation_hits_the_samples(t, seed) -> None:
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(len(t), 3)) * 1000 + [691000, 5334000, 500]
    A = rng.uniform([-40, -40, 0], [40, 40, 360], (len(t), 3))
    traj = Trajectory.from_samples(t, P, A)
    Pi, Ri = traj.at(t)
    np.testing.assert_allclose(Pi, P, rtol=0, atol=1e-9)
    np.testing.assert_allclose(Ri, ned_from_body(A), atol=1e-12)
    # between samples: positions on the chord, rotations orthonormal
    mid = (t[:-1] + t[1:]) / 2
    Pm, Rm = traj.at(mid)
    np.testing.assert_allclose(Pm, (P[:-1] + P[1:]) / 2, atol=1e-6)
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", Rm, Rm), np.broadcast_to(np.eye(3), Rm.shape), atol=1e-12
    )


@settings(max_examples=80, deadline=None, derandomize=True)
@given(h0=st.floats(350, 359.99), dh=st.floats(0.02, 15), f=st.floats(0, 1))
def test_slerp_across_the_wrap(h0, dh, f) -> None:
    h1 = (h0 + dh) % 360  # crosses north: e.g. 359.9 -> 0.1
    traj = Trajectory.from_samples([0.0, 1.0], np.zeros((2, 3)), [[0, 0, h0], [0, 0, h1]])
    _, R = traj.at(np.array([f]))
    h = attitude_from_ned_from_body(R)[0, 2]
    expected = (h0 + f * dh) % 360
    assert abs((h - expected + 180) % 360 - 180) < 1e-8


def test_slerp_359_9_to_0_1_passes_north() -> None:
    traj = Trajectory.from_samples([10.0, 11.0], np.zeros((2, 3)), [[2, 1, 359.9], [2, 1, 0.1]])
    _, R = traj.at(np.array([10.5]))
    att = attitude_from_ned_from_body(R)[0]
    assert min(att[2], 360 - att[2]) < 1e-9  # heading 0, not 180
    np.testing.assert_allclose(att[:2], [2, 1], atol=1e-3)


def test_outside_time_range_raises_unless_extrapolation_allowed() -> None:
    traj = Trajectory.from_samples([0.0, 1.0], [[0, 0, 0], [10, 0, 0]], [[0, 0, 0], [0, 0, 10]])
    with pytest.raises(GeorefError, match="outside the trajectory"):
        traj.at(np.array([1.1]))
    with pytest.raises(GeorefError):
        traj.at(np.array([-0.01]))
    P, R = traj.at(np.array([-0.2, 1.2]), max_extrapolation_s=0.2)
    np.testing.assert_allclose(P, [[-2, 0, 0], [12, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(attitude_from_ned_from_body(R)[:, 2], [358, 12], atol=1e-9)
    with pytest.raises(GeorefError, match="increasing"):
        Trajectory.from_samples([0.0, 0.0], np.zeros((2, 3)), np.zeros((2, 3)))


# -- true heading and CRS -------------------------------------------------------------------------
def grid_azimuth_of_true_north(lon: float, lat: float, crs: str) -> float:
    """Independent of get_factors: grid direction of a short step north along the meridian."""
    tr = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    x0, y0 = tr.transform(lon, lat)
    x1, y1 = tr.transform(lon, lat + 1e-5)
    return float(np.degrees(np.arctan2(x1 - x0, y1 - y0)))


@pytest.mark.parametrize("lon", [6.5, 9.0, 11.7, 14.8])
def test_convergence_sign_against_meridian_direction(lon: float) -> None:
    x, y = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True).transform(lon, 50.0)
    gamma = float(meridian_convergence_deg("EPSG:25832", x, y))
    assert gamma == pytest.approx(-grid_azimuth_of_true_north(lon, 50.0, "EPSG:25832"), abs=1e-4)
    assert np.sign(gamma) == np.sign(round(lon - 9.0, 6))  # east of the central meridian: γ > 0


def test_true_heading_is_turned_into_grid_heading() -> None:
    lon, lat = 12.5, 51.0  # 3.5° east of UTM 32's central meridian: γ ≈ 2.7°
    x, y = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True).transform(lon, lat)
    m = manifest([[x, y, 100.0]], [[0, 0, 0]], heading_reference="true")
    pose = prior_poses(m, "EPSG:25832")[0]
    _, _, z = axes(pose)
    az = np.degrees(np.arctan2(z[0], z[1]))  # grid azimuth of the optical axis
    assert az == pytest.approx(grid_azimuth_of_true_north(lon, lat, "EPSG:25832"), abs=1e-4)
    assert abs(az) > 2.0  # a real correction happened
    # the same frame with a grid heading looks along grid north
    _, _, z = axes(prior_poses(manifest([[x, y, 100.0]], [[0, 0, 0]]), "EPSG:25832")[0])
    np.testing.assert_allclose(z, NORTH, atol=1e-12)


def test_epsg4979_to_utm_with_vertical_offset() -> None:
    # lat 48°, lon 9° lies on UTM 32's central meridian: easting exactly 500000 m
    m = manifest(
        [[48.0, 9.0, 560.0], [48.001, 9.002, 561.0]],
        [[0, 0, 0]] * 2,
        crs="EPSG:4979",
        vertical_offset_m=-47.5,
    )
    W = model_positions(m, pyproj.CRS("EPSG:25832"))
    assert W[0, 0] == pytest.approx(500000.0, abs=1e-6)
    # northing on the central meridian = 0.9996 x the GRS80 meridian arc from the equator to 48°
    a, e2 = 6378137.0, 0.00669438002290
    arc, _ = quad(lambda p: a * (1 - e2) / (1 - e2 * np.sin(p) ** 2) ** 1.5, 0.0, np.radians(48.0))
    assert W[0, 1] == pytest.approx(0.9996 * arc, abs=1e-3)
    np.testing.assert_allclose(W[:, 2], [512.5, 513.5])
    ref = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True).transform(9.002, 48.001)
    np.testing.assert_allclose(W[1, :2], ref, atol=1e-6)
    # a compound / AdV model CRS name gives the same horizontal result
    W2 = model_positions(m, "urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH*GCG2016")
    np.testing.assert_allclose(W2, W, atol=1e-6)


def test_projected_crs_passthrough_transform_and_model() -> None:
    P = [[691000.0, 5334000.0, 520.0]]
    m = manifest(P, [[0, 0, 0]], vertical_offset_m=1.0)
    np.testing.assert_allclose(
        model_positions(m, "urn:adv:crs:ETRS89_UTM32*DE_DHHN92_NH"), [[691000, 5334000, 521]]
    )
    np.testing.assert_allclose(model_positions(m, None), [[691000, 5334000, 521]])
    np.testing.assert_allclose(model_positions(manifest(P, [[0, 0, 0]], crs="model"), "EPSG:25833"), P)
    # zone 32 -> zone 33: transformed, and back again
    W = model_positions(m, "EPSG:25833")
    back = pyproj.Transformer.from_crs("EPSG:25833", "EPSG:25832", always_xy=True).transform(W[0, 0], W[0, 1])
    np.testing.assert_allclose(back, P[0][:2], atol=1e-5)
    assert abs(W[0, 0] - 691000) > 1000 and W[0, 2] == 521
    with pytest.raises(GeorefError, match="crs"):
        model_positions(manifest(P, [[0, 0, 0]], crs="EPSG:999999"), "EPSG:25832")
    with pytest.raises(GeorefError, match="not projected"):
        model_positions(manifest([[48.0, 9.0, 1.0]], [[0, 0, 0]], crs="EPSG:4979"), None)


# -- time delay -----------------------------------------------------------------------------------
def test_prior_poses_with_time_delay_from_imu() -> None:
    # constant velocity 10 m/s north, constant yaw rate 5°/s; frames at 1 Hz, IMU at 100 Hz
    t_imu = np.arange(0.0, 4.0001, 0.01)
    P0 = np.array([691000.0, 5334000.0, 520.0])
    imu = ImuSamples(
        t_imu,
        P0 + np.outer(t_imu, [0, 10, 0]),
        np.column_stack([0 * t_imu, 0 * t_imu, (355 + 5 * t_imu) % 360]),
    )
    tf = np.array([0.5, 1.5, 2.5, 3.5])
    m = manifest(
        P0 + np.outer(tf, [0, 10, 0]),
        np.column_stack([0 * tf, 0 * tf, (355 + 5 * tf) % 360]),
        times=tf,
        imu=imu,
        mnt=mounting(lever=(2.0, 0, 0)),
    )
    delay = 0.137
    poses = prior_poses(m, "EPSG:25832", time_delay_s=delay)
    for k, t in enumerate(tf - delay):
        h = np.radians(355 + 5 * t)
        expected_c = P0 + [0, 10 * t, 0] + 2.0 * np.array([np.sin(h), np.cos(h), 0])
        np.testing.assert_allclose(poses[k].center, expected_c, atol=1e-6)
        _, _, z = axes(poses[k])
        np.testing.assert_allclose(z, [np.sin(h), np.cos(h), 0], atol=1e-9)
    # the world trajectory, built once, gives the IMU reference point at any time
    Pw, _ = world_trajectory(m, "EPSG:25832").at(tf - delay)
    np.testing.assert_allclose(Pw, P0 + np.outer(tf - delay, [0, 10, 0]), atol=1e-6)
    # no delay: exactly the frames' own solution
    zero = prior_poses(m, "EPSG:25832")
    direct = camera_poses(m.frames[0].position[None], m.frames[0].attitude_deg[None], m.mounting)[0]
    np.testing.assert_allclose(zero[0].R_world_from_cam, direct.R_world_from_cam, atol=1e-15)
    np.testing.assert_allclose(zero[0].center, direct.center, atol=1e-9)


def test_prior_poses_with_time_delay_from_frames_and_other_mounting() -> None:
    tf = np.array([0.0, 1.0, 2.0])
    P = np.array([[0.0, 0, 0], [0, 10, 0], [0, 20, 0]])
    m = manifest(P, [[0, 0, 0]] * 3, times=tf, crs="model")
    poses = prior_poses(m, None, time_delay_s=0.25, mounting=mounting(boresight=(0, 0, 90)))
    np.testing.assert_allclose([p.center for p in poses], P - [0, 2.5, 0], atol=1e-9)  # extrapolated first
    _, _, z = axes(poses[1])
    np.testing.assert_allclose(z, EAST, atol=1e-12)
    with pytest.raises(GeorefError, match="true"):
        prior_poses(manifest(P, [[0, 0, 0]] * 3, crs="model", heading_reference="true"), None)


def test_doctests() -> None:
    import doctest

    import workers.pipeline.geometry.crs
    import workers.pipeline.geometry.georef as georef

    for mod in (georef, workers.pipeline.geometry.crs):
        result = doctest.testmod(mod)
        assert result.attempted > 0 and result.failed == 0, mod.__name__


@pytest.mark.parametrize(
    "M, look, right",
    [
        ([[0, 0, 1], [1, 0, 0], [0, 1, 0]], NORTH, EAST),  # forward
        ([[-1, 0, 0], [0, 0, 1], [0, 1, 0]], EAST, -NORTH),  # to the right
        ([[1, 0, 0], [0, 0, -1], [0, 1, 0]], -EAST, NORTH),  # to the left
        ([[0, -1, 0], [1, 0, 0], [0, 0, 1]], -UP, EAST),  # down, image top forward
    ],
)
def test_mountings_documented_in_docs(M, look, right) -> None:
    """The table of common mountings in docs/sequence-format.md (heading 0: forward = north)."""
    M = np.asarray(M, float)
    assert np.linalg.det(M) == pytest.approx(1.0)
    x, _, z = axes(camera_pose([0, 0, 0], [0, 0, 0], mounting(M=M)))
    np.testing.assert_allclose(z, look, atol=1e-12)
    np.testing.assert_allclose(x, right, atol=1e-12)


def test_world_is_east_north_even_for_northing_first_crs() -> None:
    # EPSG:31467 (Gauss-Krüger zone 3) lists northing first; world x must still be the easting
    m = manifest([[48.0, 9.0, 100.0]], [[0, 0, 0]], crs="EPSG:4979")
    W = model_positions(m, "EPSG:31467")
    assert abs(W[0, 0] - 3_500_000) < 200 and abs(W[0, 1] - 5_318_000) < 2_000
    P = manifest([[3_500_000.0, 5_318_000.0, 10.0]], [[0, 0, 0]], crs="EPSG:31467")
    W = model_positions(P, "EPSG:25832")
    assert abs(W[0, 0] - 500_000) < 200 and abs(W[0, 1] - 5_316_300) < 2_000
