"""The order in which the prepare task queues a job's building units (`service_job.dispatch_order`):
costliest first by `unit_cost` (texels of the building's surfaces, frames), plan order among
equals; the polygon area it rests on; and the plan made while other workers orient windows
(`service_job.with_sequence`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest

from workers import service_job as sj
from workers.pipeline.geometry.citymodel import Building, Polygon, Ring
from workers.pipeline.units import UnitOptions


def wall(width: float, height: float) -> Polygon:
    """A vertical rectangle `width` × `height` m, at UTM-sized coordinates, tilted 30° about z."""
    a = np.radians(30.0)
    u = np.array([np.cos(a), np.sin(a), 0.0])
    o, up = np.array([390000.0, 5820000.0, 34.0]), np.array([0.0, 0.0, height])
    pts = [o, o + width * u, o + width * u + up, o + up, o]
    return Polygon(f"p{width}x{height}", Ring("r", np.array(pts)))


@dataclass(frozen=True)
class StandInUnit:
    """What `unit_cost` reads of a `BuildingUnit`: the building, frames and options."""

    building: Building
    frames: tuple[int, ...]
    options: UnitOptions = field(default_factory=UnitOptions)


def unit(name: str, walls: list[tuple[float, float]], frames: int) -> StandInUnit:
    return StandInUnit(Building(name, polygons=tuple(wall(w, h) for w, h in walls)), tuple(range(frames)))


def test_polygon_area_of_a_tilted_wall_at_utm_coordinates() -> None:
    assert sj.polygon_area_m2(wall(12.0, 7.5).exterior.coords) == pytest.approx(90.0, rel=1e-9)
    open_ring = wall(12.0, 7.5).exterior.coords[:-1]  # not closed: the same area
    assert sj.polygon_area_m2(open_ring) == pytest.approx(90.0, rel=1e-9)


def test_unit_cost_counts_texels_at_the_units_resolution_and_frames() -> None:
    u = unit("a", [(10.0, 10.0), (20.0, 5.0)], frames=8)  # 200 m² at 10 texels/m: 20 000 texels
    expected = sj.COST_PER_MEGATEXEL_S * 0.02 + sj.COST_PER_FRAME_S * 8
    assert sj.unit_cost(u) == pytest.approx(expected, rel=1e-9)  # type: ignore[arg-type]


def test_costliest_units_are_queued_first_plan_order_among_equals() -> None:
    units = [
        unit("small", [(5.0, 5.0)], frames=3),
        unit("many-frames", [(5.0, 5.0)], frames=40),  # 1.6 s
        unit("large", [(1000.0, 20.0), (500.0, 20.0)], frames=5),  # 3 million texels: 2.6 s
        unit("small-too", [(5.0, 5.0)], frames=3),
    ]
    assert sj.dispatch_order(units) == ["large", "many-frames", "small", "small-too"]  # type: ignore[arg-type]
    assert sj.dispatch_order([]) == []


def test_the_order_shortens_the_last_units_on_two_workers() -> None:
    """List scheduling on 2 workers (each takes the next queued unit when free): plan order with the
    largest unit last ends later than the dispatch order."""
    units = [unit(f"u{k}", [(5.0, 5.0)], frames=10) for k in range(6)] + [unit("big", [(60.0, 30.0)], 40)]
    cost = {u.building.id: sj.unit_cost(u) for u in units}  # type: ignore[arg-type]

    def makespan(order: list[str]) -> float:
        free = [0.0, 0.0]
        for b in order:
            k = int(np.argmin(free))
            free[k] += cost[b]
        return max(free)

    plan = [u.building.id for u in units]
    queued = sj.dispatch_order(units)  # type: ignore[arg-type]
    assert sorted(queued) == sorted(plan)
    assert makespan(queued) < makespan(plan)
    # the longest-processing-time rule on 2 workers: within 7/6 of the best schedule, which
    # takes at least the largest unit and at least half of all
    best_bound = max(max(cost.values()), sum(cost.values()) / 2)
    assert makespan(queued) <= 7 / 6 * best_bound + 1e-12


def test_resolution_of_the_unit_options_scales_the_texel_term() -> None:
    coarse = unit("c", [(10.0, 10.0)], frames=0)
    twenty = SimpleNamespace(texel=SimpleNamespace(resolution_px_per_m=20.0))
    fine = StandInUnit(coarse.building, (), twenty)  # type: ignore[arg-type]
    assert sj.unit_cost(fine) == pytest.approx(4 * sj.unit_cost(coarse))  # type: ignore[arg-type]


def test_planned_before_the_orientation_then_given_it_equals_the_plan_with_it() -> None:
    """The prepare task plans while other workers orient windows (`service_job.with_sequence`):
    the same units as `workers.job.plan` with the orientation."""
    from pathlib import Path

    from workers import job
    from workers.pipeline.geometry.citymodel import ModelHeader
    from workers.pipeline.geometry.manifest import MemoryFrames
    from workers.pipeline.geometry.pose import Pose
    from workers.pipeline.orientation.sequence import SequenceOrientation
    from workers.pipeline.orientation.tracks import Tracks
    from workers.pipeline.synth import SynthOptions, procedural_block, synthesize

    drive = SynthOptions(platform="drive", n_frames=12, seed=1, buildings=2)
    res = synthesize(procedural_block(4, seed=1), drive)
    m, priors, blds = res.manifest, tuple(res.truth.poses), tuple(res.buildings)
    ing = job.Ingested(Path("<synthetic>"), Path("<memory>"), ModelHeader("2.0"), m,
                       MemoryFrames({}), priors, blds, len(blds), m.radiometry)  # fmt: skip
    cal = job.Calibrated(None, priors, m.accuracy)
    rng = np.random.default_rng(2)
    oriented_frames = range(0, 12, 2)  # a stand-in orientation of every other frame
    so = SequenceOrientation(
        poses={f: Pose(p.R_world_from_cam, p.center + rng.normal(0, 0.1, 3)) if f in oriented_frames else p
               for f, p in enumerate(priors)},
        covariance={f: np.eye(6) * (1e-4 + f) for f in oriented_frames},
        blocks=[], tracks=Tracks.empty(), ties=dict.fromkeys(oriented_frames, 30),
        tie_rms_px=dict.fromkeys(oriented_frames, 0.4),
    )  # fmt: skip
    options = job.RunOptions()
    direct = job.plan(ing, cal, job.Oriented(so, {"run": True}), options)
    early = sj.with_sequence(job.plan(ing, cal, job.Oriented(None, {"run": False}), options),
                             job.Oriented(so, {"run": True}))  # fmt: skip
    assert len(direct.units) >= 2 and direct.warning == early.warning
    for a, b in zip(direct.units, early.units, strict=True):
        assert (a.building.id, a.frames, a.times) == (b.building.id, b.frames, b.times)
        assert [o.id for o in a.occluders] == [o.id for o in b.occluders]
        assert a.sequence is not None and b.sequence is not None
        assert a.sequence.poses.keys() == b.sequence.poses.keys() and a.sequence.poses
        for f in a.sequence.poses:
            assert np.array_equal(a.sequence.poses[f].center, b.sequence.poses[f].center)
            assert np.array_equal(a.sequence.covariance[f], b.sequence.covariance[f])
        assert (a.sequence.ties, a.sequence.tie_rms_px) == (b.sequence.ties, b.sequence.tie_rms_px)
    # no orientation (the stage did not run or failed): the early plan as it is
    none = job.plan(ing, cal, job.Oriented(None, {"run": False}), options)
    assert sj.with_sequence(none, job.Oriented(None, {"run": False})) is none
