"""Truth-based evaluation of anomaly detections (`workers.anomaly_eval`) with hand-made
detections on one wall: matching, observed share, precision/recall, IoU, ΔT, false-leak rate."""

from __future__ import annotations

import doctest

import numpy as np
import pytest

import workers.anomaly_eval as ev
from workers.anomaly_eval import (
    Coverage,
    detections_from_geojson,
    evaluate_leaks,
    evaluate_windows,
    false_leak_rate,
    greedy_match,
    leaks_on_windows,
    ring_iou,
)
from workers.pipeline.results import Anomaly as Detected
from workers.pipeline.synth import gable_house
from workers.pipeline.synth.anomaly import HALF_MAX_SIGMAS, Anomaly, Window
from workers.pipeline.texture.texel import TexelOptions, texel_grid

HOUSE = gable_house("h", 12.0, 8.0, 6.0, 9.0, np.zeros(3))
WALL = next(p for p in HOUSE.polygons if p.id == "h-wall-s")  # y = 0, x 0..12, z 0..6, normal -y
GRID = texel_grid(WALL, "h", TexelOptions(resolution_px_per_m=10.0))
SIGMA = 0.5
R = HALF_MAX_SIGMAS * SIGMA


def leak(i: int, x: float, z: float, peak: float = 3.0) -> Anomaly:
    a = Anomaly(f"leak-h-{i}", "h", WALL.id, "WallSurface", np.array([x, 0.0, z]), SIGMA, peak)
    return a.with_outline(WALL)


def window(x0: float, z0: float, w: float = 1.2, h: float = 1.4) -> Window:
    ring = np.array([[x0, 0, z0], [x0 + w, 0, z0], [x0 + w, 0, z0 + h], [x0, 0, z0 + h], [x0, 0, z0]], float)
    return Window(f"window-{x0}-{z0}", "h", WALL.id, 0, 0, ring, ring[:4].mean(axis=0), w, h, -2.5)


def disc(centre: np.ndarray, r: float, n: int = 128) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n + 1)
    return np.asarray(centre) + r * np.stack([np.cos(a), np.zeros_like(a), np.sin(a)], axis=1)


def det(centre, peak: float = 3.0, kind: str = "leak", outline: np.ndarray | None = None) -> Detected:
    c = np.asarray(centre, float)
    ring = disc(c, R) if outline is None else outline
    return Detected("h", WALL.id, ring, c, 1.0, peak, 0.5 * peak, kind)


def coverage(observed_from_x: float = -1.0, one_frame_from_x: float = 99.0, grid=GRID) -> Coverage:
    """The wall observed where x > `observed_from_x` (NaN elsewhere), by 3 frames, but by one
    frame only where x > `one_frame_from_x`."""
    r, c = np.indices(grid.shape)
    x = grid.centres(r.ravel(), c.ravel())[:, 0].reshape(grid.shape)
    value = np.where(grid.mask & (x > observed_from_x), 276.0, np.nan).astype(np.float32)
    frames = np.where(np.isfinite(value), np.where(x > one_frame_from_x, 1, 3), 0)
    return Coverage({WALL.id: (grid, value)}, {WALL.id: frames})


TRUTH = [leak(0, 3.0, 3.0), leak(1, 8.0, 2.0)]


def test_greedy_match_is_one_to_one_by_distance():
    assert doctest.testmod(ev).failed == 0
    D = np.array([[0.0, 0, 0], [0.1, 0, 0], [5.0, 0, 0]])
    T = np.array([[0.15, 0, 0], [0.45, 0, 0]])
    m = greedy_match(D, T, 0.5)
    assert [(i, j) for i, j, _ in m] == [(1, 0), (0, 1)]  # 0.05 first, then 0.45; 5 m: none
    assert greedy_match(D, np.zeros((0, 3)), 0.5) == []
    assert greedy_match(D[:1], T[1:], 0.4) == []
    assert [(i, j) for i, j, _ in greedy_match(D[:1], T[1:], 0.4, {(0, 0): True})] == [(0, 0)]


def test_perfect_detections():
    dets = [det(a.center, a.peak_k, outline=a.outline) for a in TRUTH]
    f = evaluate_leaks(TRUTH, dets, coverage())
    assert (f["truth_observed"], f["matched"], f["false"]) == (2, 2, 0)
    assert f["precision"] == 1.0 and f["recall"] == 1.0
    assert f["outline_iou_median"] == pytest.approx(1.0) and f["delta_k_error_median_k"] == 0.0
    assert f["false_leaks_per_100m2_facade"] == 0.0


def test_centre_within_half_a_metre_and_delta_k_error():
    dets = [
        det(TRUTH[0].center + np.array([0.4, 0, 0]), peak=3.2),
        det(TRUTH[1].center + np.array([0, 0, 0.6]), peak=2.5),
    ]
    f = evaluate_leaks(TRUTH, dets, coverage())
    assert (f["matched"], f["false"]) == (1, 1)
    assert f["precision"] == 0.5 and f["recall"] == 0.5 and f["missed"] == ["leak-h-1"]
    assert f["delta_k_error_median_k"] == pytest.approx(0.2, abs=1e-4)
    assert f["centre_error_median_m"] == pytest.approx(0.4, abs=1e-4)
    # a matched leak's outline IoU: two discs of radius R, 0.4 m apart (lens area over union)
    d = 0.4
    lens = 2 * R**2 * np.arccos(d / (2 * R)) - 0.5 * d * np.sqrt(4 * R**2 - d**2)
    assert f["outline_iou_median"] == pytest.approx(lens / (2 * np.pi * R**2 - lens), abs=0.01)
    # the delta-k median over two matches
    dets = [det(TRUTH[0].center, peak=3.2), det(TRUTH[1].center, peak=2.5)]
    assert evaluate_leaks(TRUTH, dets, coverage())["delta_k_error_median_k"] == pytest.approx(0.35, abs=1e-4)


def test_two_detections_on_one_leak_one_is_false():
    dets = [
        det(TRUTH[0].center + np.array([0, 0, 0.2]), peak=1.0),
        det(TRUTH[0].center + np.array([0.1, 0, 0]), peak=3.0),
    ]
    f = evaluate_leaks(TRUTH[:1], dets, coverage())
    assert (f["matched"], f["false"], f["precision"]) == (1, 1, 0.5)
    assert f["delta_k_error_median_k"] == 0.0  # the nearer one (peak 3.0) is the match
    assert f["false_examples"] == [
        {"surface": WALL.id, "centre": [3.0, 0.0, 3.2], "peak_delta_k": 1.0, "nearest_truth_leak_m": 0.2}
    ]


def test_windows_and_bridges_are_not_leaks():
    dets = [det(a.center, kind="window") for a in TRUTH] + [det(TRUTH[0].center, kind="bridge")]
    f = evaluate_leaks(TRUTH, dets, coverage())
    assert (f["detections"], f["matched"], f["recall"], f["precision"]) == (0, 0, 0.0, None)


def test_observed_share_and_unobserved_leaks():
    cov = coverage(observed_from_x=6.0)  # the leak at x = 3 was not observed, the one at x = 8 was
    assert cov.observed_share(WALL.id, TRUTH[0].outline) == 0.0
    assert cov.observed_share(WALL.id, TRUTH[1].outline) == 1.0
    assert cov.observed_share(WALL.id, leak(2, 6.0, 3.0).outline) == pytest.approx(0.5, abs=0.05)
    assert cov.observed_share("other", TRUTH[1].outline) == 0.0
    tiny = disc(np.array([8.02, 0, 2.02]), 0.01)  # smaller than a texel: the texel under it
    assert cov.observed_share(WALL.id, tiny) == 1.0
    assert coverage(observed_from_x=9.0).observed_share(WALL.id, tiny) == 0.0
    dets = [det(a.center) for a in TRUTH]
    f = evaluate_leaks(TRUTH, dets, cov)
    assert f["truth_observed"] == 1 and f["matched"] == 1 and f["matched_unobserved_ignored"] == 1
    assert f["precision"] == 1.0 and f["recall"] == 1.0 and f["false"] == 0
    # 60 % of the disc observed counts (>= 50 %), 40 % does not (centre 0.157 R off the edge)
    more, less = leak(2, 6.0 + 0.157 * R, 3.0), leak(3, 6.0 - 0.157 * R, 3.0)
    assert cov.observed_share(WALL.id, more.outline) == pytest.approx(0.6, abs=0.05)
    assert cov.observed_share(WALL.id, less.outline) == pytest.approx(0.4, abs=0.05)
    assert evaluate_leaks([more, less], [], cov)["truth_observed"] == 1


def test_observed_needs_two_frames_and_a_resolvable_size():
    # the leak at x = 8 lies where one frame only saw the wall: not observed (the detector may
    # not report it), but observed by the earlier definition
    cov = coverage(one_frame_from_x=6.0)
    assert cov.observed_share(WALL.id, TRUTH[1].outline) == 1.0
    assert cov.observed_share(WALL.id, TRUTH[1].outline, min_frames=2) == 0.0
    assert cov.observed_share(WALL.id, TRUTH[0].outline, min_frames=2) == 1.0
    f = evaluate_leaks(TRUTH, [det(a.center) for a in TRUTH], cov)
    assert (f["truth_observed"], f["matched"], f["matched_unobserved_ignored"]) == (1, 1, 1)
    old = evaluate_leaks(TRUTH, [det(a.center) for a in TRUTH], cov, ev.EvalOptions.texels_only())
    assert (old["truth_observed"], old["matched"]) == (2, 2)
    # without frame counts only the earlier definition applies
    bare = Coverage(cov.textures)
    with pytest.raises(ValueError, match="frame counts"):
        evaluate_leaks(TRUTH, [], bare)
    assert evaluate_leaks(TRUTH, [], bare, ev.EvalOptions.texels_only())["truth_observed"] == 2
    # resolvable: the half-maximum diameter (2 · 1.177 · 0.5 = 1.18 m) spans >= 2 texels at
    # 0.5 m, not at 0.6 m; a 1.2 x 1.4 m pane spans >= 3 texels a side at 0.4 m, not at 0.5 m
    for size, leaks_seen, panes_seen in ((0.4, 2, 1), (0.5, 2, 0), (0.6, 0, 0)):
        grid = texel_grid(WALL, "h", TexelOptions(resolution_px_per_m=1.0 / size))
        cov = coverage(grid=grid)
        assert evaluate_leaks(TRUTH, [], cov)["truth_observed"] == leaks_seen, size
        assert evaluate_windows([window(4.0, 1.0)], [], cov)["truth_observed"] == panes_seen, size
        old = ev.EvalOptions.texels_only()
        assert evaluate_leaks(TRUTH, [], cov, old)["truth_observed"] == 2


def test_window_matching_by_centre_or_iou():
    truth = [window(1.0, 1.0), window(4.0, 1.0), window(7.0, 1.0)]

    def rect(x0: float, z0: float, w: float, h: float) -> np.ndarray:
        return window(x0, z0, w, h).outline

    near = det(truth[0].center + np.array([0.3, 0, 0]), kind="window", outline=rect(1.3, 1.0, 1.2, 1.4))
    tall = rect(4.0, 1.0, 1.2, 2.6)  # 1.2 m taller: centre 0.6 m off, IoU 1.68 / 3.12 = 0.54
    by_iou = det(tall[:4].mean(axis=0), kind="window", outline=tall)
    wide = rect(7.55, 1.0, 1.2, 1.4)  # 0.55 m off, IoU 0.65 / 1.75 = 0.37: no match
    miss = det(wide[:4].mean(axis=0), kind="window", outline=wide)
    assert ring_iou(truth[1].outline, tall) == pytest.approx(1.68 / 3.12, abs=1e-6)
    f = evaluate_windows(truth, [near, by_iou, miss, det(truth[2].center)], coverage())
    assert (f["detections"], f["matched"], f["false"]) == (3, 2, 1)
    assert f["precision"] == pytest.approx(2 / 3, abs=1e-4) and f["recall"] == pytest.approx(2 / 3, abs=1e-4)
    f = evaluate_windows(truth, [near, by_iou], coverage(observed_from_x=3.5))
    assert (f["truth_observed"], f["matched"], f["matched_unobserved_ignored"]) == (2, 1, 1)
    assert f["precision"] == 1.0 and f["recall"] == 0.5


def test_false_leak_rate_and_leaks_on_windows():
    cov = coverage()
    area = cov.observed_area_m2(["WallSurface"])
    assert area == pytest.approx(12.0 * 6.0, rel=0.01)  # the wall, texel-counted
    assert cov.observed_area_m2(["RoofSurface"]) == 0.0
    win = window(4.0, 1.0)
    dets = [det([2.0, 0, 2.0]), det(win.center + np.array([0, 0, 0.5])), det([10.0, 0, 4.0], kind="window")]
    f = false_leak_rate(dets, cov)
    assert f["false_leaks_facade"] == 2
    assert f["false_leaks_per_100m2_facade"] == pytest.approx(200.0 / area, abs=1e-3)
    assert false_leak_rate(dets, cov, matched={0})["false_leaks_facade"] == 1
    assert leaks_on_windows(dets, [win]) == 1
    assert leaks_on_windows([det(win.center + np.array([0, 0, 1.0]))], [win]) == 0  # 0.3 m above it
    f = evaluate_leaks([], dets, cov)  # a leak-free scene
    assert f["false"] == 2 and f["precision"] == 0.0 and f["recall"] is None


def test_detections_from_geojson():
    ring = disc(np.array([3.0, 0, 3.0]), R)
    doc = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "geometry": {"type": "Polygon", "coordinates": [ring.tolist()]},
                "properties": {"building": "h", "surface": WALL.id, "centre": [3.0, 0.0, 3.0],
                               "area_m2": 1.1, "peak_delta_k": 2.9, "mean_delta_k": 1.5, "kind": "leak"},
            },
            {
                "type": "Feature",
                "geometry": {"type": "Polygon", "coordinates": [ring.tolist()]},
                "properties": {"building": "h", "surface": WALL.id, "centre": [9.0, 0.0, 3.0],
                               "area_m2": 1.1, "peak_delta_k": -2.4, "mean_delta_k": -2.0},
            },
        ],
    }  # fmt: skip
    dets = detections_from_geojson(doc)
    assert [d.kind for d in dets] == ["leak", "leak"] and dets[1].peak_delta_k == -2.4
    assert np.allclose(dets[0].outline, ring) and dets[0].polygon_id == WALL.id
    f = evaluate_leaks(TRUTH, dets, coverage())
    assert (f["matched"], f["false"]) == (1, 1)
    assert f["delta_k_error_median_k"] == pytest.approx(0.1, abs=1e-4)
