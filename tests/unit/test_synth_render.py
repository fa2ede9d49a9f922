"""Renderer geometry and radiometry against the spec's projection (synthetic scenes, fixed seeds)."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from db.citygml.reader import read_model
from tests.conftest import DATA
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.polygons import triangulate
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.synth import (
    SKY,
    Renderer,
    SensorOptions,
    ThermalOptions,
    ThermalScene,
    gable_house,
    procedural_block,
)

# a strongly distorted small camera (barrel + tangential): exercises the spec's full model
CAM = Camera(
    width=160, height=128, fx=150.0, fy=152.0, cx=80.3, cy=62.7, k1=-0.2, k2=0.05, p1=0.002, p2=-0.0015
)
NO_SENSOR = SensorOptions(psf_sigma_px=0, netd_k=0, column_noise_k=0, vignetting_k=0)
# flat field: buildings 300 K, everything else 250 K
FLAT = ThermalOptions(
    wall_k=300.0, roof_k=300.0, other_k=300.0, building_sigma_k=0.0, surface_sigma_k=0.0,
    ground_k=250.0, sky_zenith_k=250.0, sky_horizon_k=250.0, features=False,
)  # fmt: skip


def look_at(center: np.ndarray, target: np.ndarray) -> Pose:
    """Camera at `center` looking at `target`, image rows level (camera y down)."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose(np.stack([x, y, z], axis=1), center)


def expected_silhouette(pose: Pose, buildings: list) -> shapely.Geometry:
    """The spec's projection of the buildings' outline: union of every triangle projected to
    normalised coordinates (x/z, y/z), boundary densified and mapped through the distortion."""
    tris = []
    for b in buildings:
        for poly in b.iter_polygons():
            v, t = triangulate(poly)
            if len(t) == 0:
                continue
            xc = pose.cam_from_world(v)
            assert np.all(xc[:, 2] > 0)
            ab = xc[:, :2] / xc[:, 2:3]
            tris += [shapely.Polygon(ab[tt]) for tt in t]
    region = shapely.union_all([t.buffer(0) for t in tris if t.area > 0]).buffer(0)
    dense = shapely.segmentize(region, 0.0005)  # ~0.08 px
    return shapely.transform(dense, lambda ab: CAM.pixel_from_normalized(ab))


def centre_label_errors(renderer: Renderer, pose: Pose, silhouette: shapely.Geometry) -> np.ndarray:
    """Distances (px) to the projected outline of the pixel centres the renderer classifies
    differently from the projection (building vs background)."""
    label, _ = renderer.labels(pose)
    v, u = np.mgrid[0 : CAM.height, 0 : CAM.width].astype(float)
    inside = shapely.contains_xy(silhouette, u.ravel(), v.ravel())
    rendered = label.ravel() >= 0
    assert inside.sum() > 500 and (~inside).sum() > 500  # the building fills part of the frame
    bad = np.flatnonzero(inside != rendered)
    pts = shapely.points(u.ravel()[bad], v.ravel()[bad])
    return shapely.distance(silhouette.boundary, pts)


@pytest.fixture(scope="module")
def box():
    house = gable_house("box", 12.0, 8.0, 9.0, 9.0, np.array([500000.0, 5400000.0, 100.0]), 0.3)
    mesh = build_scene_mesh([house])
    thermal = ThermalScene([house], mesh.polygon_ids, seed=1, options=FLAT)
    pose = look_at(np.array([500004.0, 5399978.0, 104.0]), np.array([500004.0, 5400004.0, 104.5]))
    return house, mesh, thermal, pose


def test_box_silhouette_pixel_centres(box):
    house, mesh, thermal, pose = box
    r = Renderer(mesh, thermal, CAM, ground_z=-1e4, sensor=NO_SENSOR)
    sil = expected_silhouette(pose, [house])
    err = centre_label_errors(r, pose, sil)
    assert err.size == 0 or err.max() < 0.5


def test_box_silhouette_subpixel_edges(box):
    """Area-sampled edges (4×4 rays per pixel) lie within 0.5 px (in fact ~0.1 px) of the
    distorted projection of the box's silhouette, row by row."""
    house, mesh, thermal, pose = box
    r = Renderer(mesh, thermal, CAM, ground_z=-1e4, sensor=SensorOptions(0, 0, 0, 0, supersample=4))
    cover = (r.radiance(pose).astype(float) - 250.0) / 50.0
    sil = expected_silhouette(pose, [house])
    assert isinstance(sil, shapely.Polygon)
    errors = []
    for v in range(CAM.height):
        row = cover[v]
        line = shapely.LineString([(-10, v), (CAM.width + 10, v)])
        cut = shapely.intersection(sil.boundary, line)
        xs = np.sort([p.x for p in getattr(cut, "geoms", [cut]) if not p.is_empty])
        if len(xs) != 2 or xs[0] < 2 or xs[1] > CAM.width - 3:
            continue
        # only rows where both edges are steep (cross the row within one pixel)
        steep = True
        for x in xs:
            near = shapely.intersection(sil.boundary, shapely.box(x - 3, v - 1, x + 3, v + 1))
            c = shapely.get_coordinates(near)
            if len(c) < 2 or np.ptp(c[:, 0]) > 0.6 * max(np.ptp(c[:, 1]), 1e-9):
                steep = False
        if not steep:
            continue
        on = np.flatnonzero(row > 0.01)
        i0, i1 = on[0], on[-1]
        left = i0 - 0.5 + (1.0 - row[i0])
        right = i1 - 0.5 + row[i1]
        errors += [left - xs[0], right - xs[1]]
    errors = np.abs(errors)
    assert len(errors) > 40
    assert errors.max() < 0.5
    assert errors.mean() < 0.2


def test_real_lod2_building_silhouette():
    _, blds = read_model(DATA / "bavaria-1-building-citygml2-lod2.gml")
    mesh = build_scene_mesh(blds)
    thermal = ThermalScene(blds, mesh.polygon_ids, seed=2, options=FLAT)
    lo, hi = blds[0].bounds()
    c = 0.5 * (lo + hi)
    size = float(np.max(hi - lo))
    pose = look_at(c + np.array([-1.1 * size, -1.4 * size, 0.7 * size]), c)
    r = Renderer(mesh, thermal, CAM, ground_z=-1e4, sensor=NO_SENSOR)
    sil = expected_silhouette(pose, blds)
    err = centre_label_errors(r, pose, sil)
    assert err.size == 0 or err.max() < 0.5


def test_flat_patch_radiometry():
    """Pixels on flat parts of the field (all features but the fine texture) return the field's
    temperature at the ray's hit point (an independent ray cast through `RayCaster`) within
    3 × NETD; the noise has the NETD."""
    blds = procedural_block(4, seed=3)
    mesh = build_scene_mesh(blds)
    thermal = ThermalScene(blds, mesh.polygon_ids, seed=3, options=ThermalOptions(texture_amplitude_k=0.0))
    netd = 0.05
    sensor = SensorOptions(psf_sigma_px=0.6, netd_k=netd, column_noise_k=0.0, vignetting_k=0.0)
    gz = float(blds[0].bounds()[0][2])
    r = Renderer(mesh, thermal, CAM, ground_z=gz, sensor=sensor, seed=4)
    lo, hi = blds[1].bounds()
    target = 0.5 * (lo + hi)
    pose = look_at(target + np.array([3.0, -25.0, -3.0]), target)
    ideal = r.radiance(pose)
    img = r.frame(pose, 0)
    # smooth pixels: the 5x5 neighbourhood of the ideal image varies by < 0.01 K, on a building
    from scipy.ndimage import maximum_filter, minimum_filter

    flat = (maximum_filter(ideal, 5) - minimum_filter(ideal, 5)) < 0.01
    label, _ = r.labels(pose)
    v, u = np.nonzero(flat & (label >= 0))
    assert len(v) > 300
    rays = pose.R_world_from_cam @ CAM.bearing(np.stack([u, v], axis=-1).astype(float)).T
    hits = RayCaster(mesh).cast(np.broadcast_to(pose.center, (len(v), 3)), rays.T)
    assert np.all(hits.hit)
    X = pose.center + hits.t[:, None] * rays.T
    truth = thermal.temperature(X, hits.polygon)
    err = img[v, u] - truth
    assert np.mean(np.abs(err) < 3 * netd) > 0.99
    assert abs(np.mean(err)) < 0.2 * netd
    assert 0.85 * netd < np.std((img - ideal)[flat]) < 1.15 * netd


def test_sensor_effects_follow_their_parameters():
    """Mean over frames = vignetting · r² + a column offset: the fitted vignetting and the spread
    of the column offsets match the parameters; the frame-to-frame noise has the NETD."""
    blds = procedural_block(2, seed=5)
    mesh = build_scene_mesh(blds)
    thermal = ThermalScene(blds, mesh.polygon_ids, seed=5)
    sensor = SensorOptions(psf_sigma_px=0.0, netd_k=0.05, column_noise_k=0.04, vignetting_k=-0.3)
    r = Renderer(mesh, thermal, CAM, ground_z=0.0, sensor=sensor, seed=6)
    ideal = np.full((CAM.height, CAM.width), 280.0, np.float32)
    frames = np.stack([r.apply_sensor(ideal, i) for i in range(40)]).astype(np.float64)
    assert np.array_equal(frames[3], r.apply_sensor(ideal, 3))  # deterministic per frame index
    mean = frames.mean(axis=0) - 280.0
    v, u = np.mgrid[0 : CAM.height, 0 : CAM.width].astype(float)
    r2 = ((u - CAM.cx) ** 2 + (v - CAM.cy) ** 2) / (CAM.cx**2 + CAM.cy**2)  # 1 at the corners
    x, y = r2 - r2.mean(axis=0), mean - mean.mean(axis=0)  # per-column offsets removed
    slope = float((x * y).sum() / (x * x).sum())
    assert abs(slope - (-0.3)) < 0.01
    cols = mean.mean(axis=0) - slope * r2.mean(axis=0)
    assert 0.8 * 0.04 < np.std(cols) < 1.2 * 0.04
    # temporal noise: the frame-to-frame difference has std √2 · NETD
    assert 0.047 < np.std(frames[1] - frames[0]) / np.sqrt(2) < 0.053


def test_sky_and_ground_labels():
    house = gable_house("h", 10.0, 8.0, 6.0, 9.0, np.array([0.0, 0.0, 0.0]))
    mesh = build_scene_mesh([house])
    r = Renderer(mesh, ThermalScene([house], mesh.polygon_ids), CAM, ground_z=0.0, sensor=NO_SENSOR)
    label, depth = r.labels(look_at(np.array([5.0, -30.0, 2.0]), np.array([5.0, 0.0, 2.0])))
    assert np.all(label[0] == SKY) and np.all(np.isinf(depth[0]))
    assert np.all(label[-1] == -2)  # the bottom row sees the ground plane
    assert (label >= 0).sum() > 1000


def test_adaptive_area_sampling_matches_full_area_sampling() -> None:
    """Sub-pixel rays only where a neighbour differs (adaptive, the default) against 3 × 3 rays in
    every pixel, on a drive frame with windows and a thermal pattern: the same image but for a
    few pixels where a feature thinner than a pixel lies between two pixel centres (0.05 % differ
    by more than 0.1 K), where one ray per pixel differs in 3 % of the pixels."""
    from workers.pipeline.synth import SynthOptions, procedural_block, synthesize

    res = synthesize(procedural_block(6, seed=1),
                     SynthOptions(platform="drive", n_frames=2, seed=1, buildings=2))
    r = res.renderer
    images = []
    for adaptive in (True, False):
        sensor = SensorOptions(0, 0, 0, 0, supersample=3, adaptive=adaptive)
        images.append(Renderer(r.mesh, r.thermal, r.camera, r.ground_z, sensor).radiance(res.truth.poses[1]))
    d = np.abs(images[0].astype(float) - images[1].astype(float))
    assert np.mean(d > 0.1) < 0.002 and np.percentile(d, 99.9) < 0.05 and np.sqrt(np.mean(d**2)) < 0.05
    single = Renderer(r.mesh, r.thermal, r.camera, r.ground_z, SensorOptions(0, 0, 0, 0, supersample=1))
    e = np.abs(single.radiance(res.truth.poses[1]).astype(float) - images[1])
    assert np.mean(e > 0.1) > 10 * np.mean(d > 0.1) and np.sqrt(np.mean(e**2)) > 10 * np.sqrt(np.mean(d**2))
