"""Job and unit states in the database, decided from the units; sequences with frames; poses of a
stored result linked to the job's frames and priors."""

from __future__ import annotations

import numpy as np
import pytest
from sqlalchemy import text
from sqlalchemy.orm import Session

from db.citygml.reader import read_model
from db.importer import import_citygml
from db.jobs import (
    StateError,
    add_units,
    create_job,
    dismiss_job,
    finish_job_if_done,
    job_counts,
    set_job_status,
    set_unit_status,
)
from db.sequences import register_sequence
from db.store import store_building_result
from tests.integration.conftest import TEST_SRID
from tests.integration.test_db_store_export import make_result
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.manifest import FrameRecord, Mounting, Radiometry, SequenceManifest
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.synth import BUNDLED_MODEL

pytestmark = pytest.mark.integration


def _manifest(n: int) -> SequenceManifest:
    frames = tuple(
        FrameRecord(
            i, f"frames/{i:06d}.png", 0.1 * i, np.array([392000.0 + i, 5820000.0, 40.0]), np.zeros(3)
        )
        for i in range(n)
    )
    cam = Camera(width=640, height=512, fx=800.0, fy=800.0, cx=319.5, cy=255.5)
    return SequenceManifest("car", "EPSG:25833", cam, Radiometry(), Mounting(np.eye(3)), frames)


def test_job_lifecycle_and_sequence(db_engine) -> None:
    s = import_citygml(db_engine, BUNDLED_MODEL, name="jobs-berlin")

    _, buildings = read_model(BUNDLED_MODEL)
    b0: Building = buildings[0]
    # the sequence in the model's CRS (ETRS89 / UTM 33N, as the Berlin model)
    priors = [Pose(np.eye(3), np.array([392000.0 + i, 5820000.0, 41.5])) for i in range(3)]
    with Session(db_engine) as session:
        seq = register_sequence(
            session,
            name="drive-1",
            manifest=_manifest(3),
            manifest_json={"format": "citytherm-sequence/1"},
            storage_location="/data/drive-1",
            srid=25833,
            priors=priors,
        )
        job = create_job(session, model_id=s.model_id, theme="tir", sequence_id=seq)
        assert add_units(session, job_id=job, building_gml_ids=[b.id for b in buildings[:3]]) == 3
        assert add_units(session, job_id=job, building_gml_ids=[buildings[0].id]) == 3  # idempotent
        set_job_status(session, job_id=job, status="running")
        with pytest.raises(StateError):
            set_job_status(session, job_id=job, status="accepted")
        set_unit_status(session, job_id=job, building_gml_id=buildings[1].id, status="running")
        set_unit_status(session, job_id=job, building_gml_id=buildings[1].id, status="failed", error="boom")
        assert finish_job_if_done(session, job_id=job) == "running"
        session.commit()
    with Session(db_engine) as session:
        store_building_result(
            session, job_id=job, model_id=s.model_id, result=make_result(b0, "tir", 9, Radiometry())
        )
    with Session(db_engine) as session:
        # a late duplicate delivery cannot undo the stored result
        set_unit_status(session, job_id=job, building_gml_id=b0.id, status="running")
        assert job_counts(session, job_id=job) == {
            "accepted": 1,
            "running": 0,
            "successful": 1,
            "failed": 1,
            "dismissed": 0,
        }
        set_unit_status(session, job_id=job, building_gml_id=buildings[2].id, status="failed", error="x")
        assert finish_job_if_done(session, job_id=job) == "successful"
        session.commit()
    with db_engine.connect() as c:
        j = c.execute(
            text("SELECT status, progress, finished_at IS NOT NULL, message FROM job WHERE id = :j"),
            {"j": job},
        ).one()
        assert j[:3] == ("successful", 1.0, True) and "1 of 3" in j[3]
        seq_row = c.execute(
            text(
                "SELECT frame_count, ST_NPoints(trajectory), ST_SRID(trajectory) FROM sequence WHERE id = :s"
            ),
            {"s": seq},
        ).one()
        assert tuple(seq_row) == (3, 3, TEST_SRID)
        poses = c.execute(
            text(
                "SELECT frame_index, frame_id IS NOT NULL, prior_center, refined_center FROM frame_pose "
                "WHERE job_id = :j ORDER BY frame_index"
            ),
            {"j": job},
        ).all()
    assert [p[0] for p in poses] == [0, 1] and all(p[1] for p in poses)
    for p in poses:
        np.testing.assert_array_equal(p[2], priors[p[0]].center)
    # dismissing a finished job is refused; a fresh one is dismissed with its pending units
    with Session(db_engine) as session:
        with pytest.raises(StateError):
            dismiss_job(session, job_id=job)
        session.rollback()
        job2 = create_job(session, model_id=s.model_id, theme="tir-2")
        add_units(session, job_id=job2)
        dismiss_job(session, job_id=job2)
        assert job_counts(session, job_id=job2)["dismissed"] == len(buildings)
        session.commit()


def test_sequences_in_model_and_geographic_coordinates_register(db_engine) -> None:
    """A sequence in `"model"` coordinates registers without a trajectory (its CRS is known only
    with a job's model); one in EPSG:4979 (`[lat, lon, h]`) gets its trajectory where PROJ puts
    those points in the database SRID (east, north; heights kept)."""
    import pyproj

    cam = Camera(width=640, height=512, fx=800.0, fy=800.0, cx=319.5, cy=255.5)
    latlon = [(52.52 + 1e-4 * i, 13.40, 80.0) for i in range(3)]
    frames = tuple(
        FrameRecord(i, f"frames/{i:06d}.png", 0.1 * i, np.array(p), np.zeros(3)) for i, p in enumerate(latlon)
    )
    with Session(db_engine) as s:
        in_model = register_sequence(
            s, name="jobs-in-model", manifest=SequenceManifest("car", "model", cam, Radiometry(),
            Mounting(np.eye(3)), frames), manifest_json={}, storage_location="/x", srid=0,
        )  # fmt: skip
        geo = register_sequence(
            s, name="jobs-geographic", manifest=SequenceManifest("car", "EPSG:4979", cam, Radiometry(),
            Mounting(np.eye(3)), frames), manifest_json={}, storage_location="/y", srid=4979,
        )  # fmt: skip
        s.commit()
    with db_engine.connect() as c:
        traj = text("SELECT trajectory IS NULL FROM sequence WHERE id = :s")
        none = c.execute(traj, {"s": in_model}).scalar()
        first = c.execute(
            text("SELECT ST_X(p), ST_Y(p), ST_Z(p) FROM sequence, ST_PointN(trajectory, 1) p WHERE id = :s"),
            {"s": geo},
        ).one()
    assert none is True
    x, y = pyproj.Transformer.from_crs(4326, TEST_SRID, always_xy=True).transform(13.40, 52.52)
    assert abs(first[0] - x) < 1e-3 and abs(first[1] - y) < 1e-3 and first[2] == 80.0
