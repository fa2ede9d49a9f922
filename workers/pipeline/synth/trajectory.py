"""True platform trajectories for synthetic sequences: drives around building clusters, flights,
walks along one facade.

In: buildings (model CRS, metres), a cluster choice, a ground height, `DriveOptions`,
`FlightOptions` or `TerrestrialOptions`. Out: a `PathTrajectory` (or a `LineTrajectory` for a
walk), a continuous function of time giving the true IMU
reference point `(N, 3)` (world) and the true attitude `[roll, pitch, heading]` `(N, 3)` degrees
(spec conventions: heading from grid north, NED/body z-y-x), and the nominal camera mounting
for the platform (`camera_to_body`).

Drive: a closed loop 8–15 m outside the union of the cluster's footprints (rounded corners),
driven clockwise so the buildings are on the right, checked to never enter any footprint of the
model; the camera looks right, turned forward and tilted up. Flight: a clockwise circle around
the cluster (or a racetrack of two straight strips) at 100–500 m, camera looking right ~45° down;
the platform banks in turns (coordinated turn) and the mounting compensates the circle's bank.
Terrestrial (hand-held or a tripod dolly, close range): a straight walk at 8–15 m in front of
the cluster's largest wall, parallel to it and centred on it, the wall on the right; the camera
looks right at the wall, slightly up; the hand-held camera sways.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import shapely
from shapely.geometry.polygon import orient

from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.synth.common import SynthError, rng_for
from workers.pipeline.synth.shapes import footprint

G = 9.81


@dataclass(frozen=True)
class DriveOptions:
    """A car driving around the cluster. Heights above the ground plane, metres."""

    speed_mps: float = 8.0
    height_m: float = 2.25  # IMU reference point above ground (camera 2–2.5 m)
    distance_m: float = 11.0  # from the cluster's facades; tried first, then others in 8..15
    look_forward_deg: float = 25.0  # camera turned from the right side toward the front
    look_up_deg: float = 18.0  # camera tilted up (roof lines of 2-3 storey houses in view)
    sway_deg: float = 0.3  # slow roll/pitch sway amplitude (true motion, seen by the INS)
    clearance_m: float = 1.5  # the path keeps this distance from every other footprint


@dataclass(frozen=True)
class FlightOptions:
    """A helicopter/drone flight over the cluster. Heights above the ground plane, metres."""

    pattern: Literal["circle", "strips"] = "circle"
    speed_mps: float = 20.0
    height_m: float = 200.0  # 100..500
    look_down_deg: float = 45.0  # optical axis below the horizon (compensating a circle's bank)
    sway_deg: float = 0.5


@dataclass(frozen=True)
class TerrestrialOptions:
    """A person walking along one facade with a hand-held camera. Heights above the ground plane,
    metres; angles in degrees."""

    speed_mps: float = 1.2
    height_m: float = 1.6  # IMU reference point (the camera) above ground
    distance_m: float = 10.0  # from the facade's plane, 8..15
    look_forward_deg: float = 0.0  # camera turned from the right side toward the front
    look_up_deg: float = 5.0  # camera tilted up (the ground line stays in view at 10 m)
    sway_deg: float = 0.8  # slow roll/pitch sway of the hand-held camera (true motion)


def choose_cluster(buildings: Sequence[Building], n_or_ids: int | Sequence[str], seed: int = 0) -> list[int]:
    """Indices of the cluster: the given ids, or the `n` buildings nearest to a central one
    (picked by `seed` among the quarter of buildings nearest to the model's centre)."""
    if not buildings:
        raise SynthError("buildings: the model has no buildings")
    if not isinstance(n_or_ids, int):
        index = {b.id: i for i, b in enumerate(buildings)}
        bad = [i for i in n_or_ids if i not in index]
        if bad:
            raise SynthError(f"buildings: unknown building id {bad[0]!r}")
        return [index[i] for i in n_or_ids]
    n = int(n_or_ids)
    if n < 1:
        raise SynthError(f"buildings: need at least 1 building, got {n}")
    fps = [footprint(b) for b in buildings]
    cent = np.array([np.asarray(f.centroid.coords[0]) for f in fps])
    mid = np.median(cent, axis=0)
    order = np.argsort(np.linalg.norm(cent - mid, axis=1))
    k = max(1, len(order) // 4)
    first = int(order[int(rng_for(seed, "cluster").integers(0, k))])
    # grow by footprint-to-footprint distance (keeps rows and blocks together)
    members = [first]
    rest = set(range(len(buildings))) - {first}
    while len(members) < min(n, len(buildings)):
        union = shapely.union_all([fps[i] for i in members])
        nxt = min(rest, key=lambda i: (union.distance(fps[i]), i))
        members.append(nxt)
        rest.discard(nxt)
    return members


def ground_height(buildings: Sequence[Building]) -> float:
    """Ground plane height: the median of the buildings' lowest vertices, metres."""
    return float(np.median([b.bounds()[0][2] for b in buildings]))


def _loop_around(shape: shapely.Geometry, distance: float, min_radius: float = 6.0) -> shapely.Polygon:
    """A single polygon whose outline is >= `distance` from `shape`: a closing (dilate by
    `distance + gap`, erode by `gap`) that merges gaps and rounds concave corners to at least
    `min_radius` (a car cannot turn on the spot); convex corners are arcs of radius `distance`."""
    for gap in (min_radius, 10.0, 20.0, 40.0, 80.0):
        g = shape.buffer(distance + gap, quad_segs=32).buffer(-gap, quad_segs=32)
        if isinstance(g, shapely.Polygon):
            return shapely.Polygon(g.exterior)
    return shapely.Polygon(shape.convex_hull.buffer(distance, quad_segs=32).exterior)


def drive_loop(
    buildings: Sequence[Building], cluster: Sequence[int], options: DriveOptions
) -> tuple[np.ndarray, list[int]]:
    """Closed clockwise loop `(M, 2)` (not repeating the first vertex) around the cluster that
    enters no footprint; buildings the loop would cross are added to the cluster, then other
    distances in 8–15 m are tried. Returns (loop, final cluster indices)."""
    fps = [footprint(b) for b in buildings]
    distances = [options.distance_m] + [
        d for d in (10.0, 12.0, 9.0, 14.0, 8.0, 15.0) if d != options.distance_m
    ]
    for dist in distances:
        members = list(dict.fromkeys(cluster))
        for _ in range(8):
            loop = _loop_around(shapely.union_all([fps[i] for i in members]), dist)
            ring = loop.exterior
            hits = [
                i for i, f in enumerate(fps) if i not in members and ring.distance(f) < options.clearance_m
            ]
            if not hits:
                cw = orient(loop, sign=-1.0)
                pts = np.asarray(shapely.segmentize(cw.exterior, 0.25).coords)[:-1, :2]
                return pts, members
            members += hits
    raise SynthError("buildings: no drive loop 8-15 m around the cluster avoids the other footprints")


def flight_loop(buildings: Sequence[Building], cluster: Sequence[int], options: FlightOptions) -> np.ndarray:
    """Closed clockwise loop `(M, 2)`: a circle of radius `height / tan(look_down)` around the
    cluster centre, or a racetrack whose straight legs pass the cluster on both sides."""
    shape = shapely.union_all([footprint(buildings[i]) for i in cluster])
    c = np.asarray(shape.centroid.coords[0])
    reach = options.height_m / np.tan(np.radians(options.look_down_deg))
    if options.pattern == "circle":
        a = np.linspace(0, 2 * np.pi, max(int(2 * np.pi * reach / 0.5), 64), endpoint=False)
        return c + reach * np.stack([np.cos(-a), np.sin(-a)], axis=-1)  # clockwise
    if options.pattern != "strips":
        raise SynthError(f"flight pattern must be 'circle' or 'strips', got {options.pattern!r}")
    lo = np.array(shape.bounds[:2])
    hi = np.array(shape.bounds[2:])
    half = 0.5 * (hi[0] - lo[0]) + 0.5 * reach
    track = shapely.LineString([(c[0] - half, c[1]), (c[0] + half, c[1])]).buffer(reach, quad_segs=32)
    cw = orient(track, sign=-1.0)
    return np.asarray(shapely.segmentize(cw.exterior, 0.5).coords)[:-1, :2]


def facade_walk(
    buildings: Sequence[Building], cluster: Sequence[int], options: TerrestrialOptions, duration_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """The walk along the cluster's largest wall (`WallSurface` polygon, or any polygon within 10°
    of vertical when there is none): its start `(2,)` (world XY, metres) and unit walking
    direction `(2,)`. The walk is parallel to the wall at `distance_m` on the side its normal
    (exterior ring orientation) points to, the wall on the right, centred on the wall's
    horizontal extent and `speed_mps · duration_s` long."""
    from workers.pipeline.geometry.polygons import fit_plane

    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for k in cluster:
        for poly in buildings[k].iter_polygons():
            plane = fit_plane(poly)
            if plane is None or abs(plane.normal[2]) > np.sin(np.radians(10.0)):
                continue
            wall = poly.surface_class == "WallSurface"
            score = plane.area * (2.0 if wall else 1.0)
            if best is None or score > best[0]:
                best = (score, plane.normal, np.asarray(poly.exterior.coords, dtype=np.float64))
    if best is None:
        raise SynthError("buildings: the cluster has no vertical wall to walk along")
    _, normal, ring = best
    n = np.asarray(normal[:2], dtype=np.float64) / np.linalg.norm(normal[:2])
    direction = np.array([n[1], -n[0]])  # right of the walking direction = −n: facing the wall
    along = ring[:, :2] @ direction
    centre = 0.5 * (along.min() + along.max())
    wall_d = float(np.median(ring[:, :2] @ n))  # the wall's line: n · xy = wall_d
    start = (wall_d + options.distance_m) * n + (centre - 0.5 * options.speed_mps * duration_s) * direction
    return start, direction


class LineTrajectory:
    """A platform moving at constant speed along a straight horizontal line, heading constant.

    Args:
        start: `(2,)` world XY at `t0`, metres.
        direction: `(2,)` unit walking direction (world XY).
        z: height of the IMU reference point, world metres.
        speed_mps: speed along the line.
        t0: time of `start`, seconds.
        sway_deg: amplitude of a slow roll/pitch sway (true motion).
        seed: seed of the sway phases.
    """

    def __init__(
        self,
        start: np.ndarray,
        direction: np.ndarray,
        z: float,
        speed_mps: float,
        t0: float = 0.0,
        sway_deg: float = 0.0,
        seed: int = 0,
    ) -> None:
        if speed_mps <= 0:
            raise SynthError("trajectory: need a positive speed")
        d = np.asarray(direction, dtype=np.float64)
        self.start = np.asarray(start, dtype=np.float64)
        self.direction = d / np.linalg.norm(d)
        self.z, self.speed, self.t0 = float(z), float(speed_mps), float(t0)
        self.heading_deg = float(np.mod(np.degrees(np.arctan2(self.direction[0], self.direction[1])), 360.0))
        rng = rng_for(seed, "sway")
        self.sway = float(sway_deg)
        self.sway_f = rng.uniform(0.1, 0.4, size=2)
        self.sway_phase = rng.uniform(0, 2 * np.pi, size=2)

    @property
    def mean_bank_deg(self) -> float:
        """No turns: 0."""
        return 0.0

    def state(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True IMU position `(N, 3)` world metres and attitude `(N, 3)` `[roll, pitch, heading]`
        degrees at `times` `(N,)` seconds."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        xy = self.start + self.speed * (t - self.t0)[:, None] * self.direction
        roll = self.sway * np.sin(2 * np.pi * self.sway_f[0] * t + self.sway_phase[0])
        pitch = self.sway * np.sin(2 * np.pi * self.sway_f[1] * t + self.sway_phase[1])
        att = np.stack([roll, pitch, np.full_like(t, self.heading_deg)], axis=-1)
        return np.concatenate([xy, np.full((len(t), 1), self.z)], axis=1), att


def camera_to_body(forward_deg: float, up_deg: float) -> np.ndarray:
    """Nominal mounting `M` `(3, 3)` (camera -> body) of a camera looking to the right (body +y),
    turned `forward_deg` toward body +x and tilted `up_deg` upward (negative: downward); image
    rows stay level: camera y (down in the image) in the body's x-z plane side."""
    a, b = np.radians(forward_deg), np.radians(up_deg)
    z = np.array([np.cos(b) * np.sin(a), np.cos(b) * np.cos(a), -np.sin(b)])
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


class PathTrajectory:
    """A platform moving at constant speed along a closed XY loop at constant height.

    Args:
        loop: `(M, 2)` world XY vertices of a closed loop (first vertex not repeated).
        z: height of the IMU reference point, world metres.
        speed_mps: speed along the loop.
        start_m: arc length of the position at `t0` (taken modulo the loop length).
        t0: time of `start_m`, seconds.
        bank: apply coordinated-turn roll `atan(v² κ / g)` (flights).
        sway_deg: amplitude of a slow roll/pitch sway (true motion).
        seed: seed of the sway phases.
    """

    def __init__(
        self,
        loop: np.ndarray,
        z: float,
        speed_mps: float,
        start_m: float = 0.0,
        t0: float = 0.0,
        bank: bool = False,
        sway_deg: float = 0.0,
        seed: int = 0,
    ) -> None:
        p = np.asarray(loop, dtype=np.float64)
        if len(p) < 3 or speed_mps <= 0:
            raise SynthError("trajectory: need a loop of >= 3 vertices and a positive speed")
        seg = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)
        self.loop = p
        self.arc = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.arc[-1])
        self.z, self.speed, self.t0 = float(z), float(speed_mps), float(t0)
        self.start = float(start_m) % self.length
        # smoothed heading (grid north, clockwise) at the vertices, unwrapped, over ±1 m
        k = max(1, round(1.0 / max(float(np.median(seg)), 1e-3)))
        tang = np.roll(p, -k, axis=0) - np.roll(p, k, axis=0)
        hd = np.unwrap(np.arctan2(tang[:, 0], tang[:, 1]))
        self.heading = np.append(hd, hd[-1] + _wrap(hd[0] - hd[-1]))  # at the arc lengths `arc`
        self.turn = float(self.heading[-1] - self.heading[0])  # per lap, radians (±2π)
        # curvature (rad per metre), smoothed over ~20 m for the bank angle
        kappa = np.gradient(self.heading[:-1], self.arc[:-1])
        w = max(1, round(10.0 / max(float(np.median(seg)), 1e-3)))
        ker = np.ones(2 * w + 1) / (2 * w + 1)
        kappa = np.convolve(np.concatenate([kappa[-w:], kappa, kappa[:w]]), ker, mode="valid")
        self.roll_bank = np.degrees(np.arctan(self.speed**2 * kappa / G)) if bank else np.zeros(len(p))
        rng = rng_for(seed, "sway")
        self.sway = float(sway_deg)
        self.sway_f = rng.uniform(0.1, 0.4, size=2)
        self.sway_phase = rng.uniform(0, 2 * np.pi, size=2)

    @property
    def mean_bank_deg(self) -> float:
        """Median bank angle along the loop, degrees (a circle's constant bank)."""
        return float(np.median(self.roll_bank))

    def arc_at(self, times: np.ndarray) -> np.ndarray:
        """Arc length `(N,)` (unbounded, laps continue) at `times` `(N,)` seconds."""
        return self.start + self.speed * (np.asarray(times, dtype=np.float64) - self.t0)

    def state(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True IMU position `(N, 3)` world metres and attitude `(N, 3)` `[roll, pitch, heading]`
        degrees (heading in [0, 360)) at `times` `(N,)` seconds."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        u = self.arc_at(t)
        lap = np.floor(u / self.length)
        um = u - lap * self.length
        closed = np.vstack([self.loop, self.loop[:1]])
        x = np.interp(um, self.arc, closed[:, 0])
        y = np.interp(um, self.arc, closed[:, 1])
        heading = np.interp(um, self.arc, self.heading) + lap * self.turn
        roll = np.interp(um, self.arc, np.append(self.roll_bank, self.roll_bank[0]))
        roll = roll + self.sway * np.sin(2 * np.pi * self.sway_f[0] * t + self.sway_phase[0])
        pitch = self.sway * np.sin(2 * np.pi * self.sway_f[1] * t + self.sway_phase[1])
        att = np.stack([roll, pitch, np.mod(np.degrees(heading), 360.0)], axis=-1)
        return np.stack([x, y, np.full_like(x, self.z)], axis=-1), att


def _wrap(a: float) -> float:
    """Angle difference wrapped to (−π, π]."""
    return float((a + np.pi) % (2 * np.pi) - np.pi)
