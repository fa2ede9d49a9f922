"""What the process pool's fork server imports before it forks workers (`pool.pool_context`):
the job's modules (`workers.job`: the building units' `run_unit` and, through it, the pipeline,
OpenCV and SciPy) and Open3D without its visualisation package (`open3d_light`). Each worker is a
fork of the server, so none imports them again: the units' workers used to import `workers.job`
on their first task (0.9 CPU s each), and Open3D's visualisation package cost 0.55 CPU s per
import."""

from __future__ import annotations

import workers.job  # noqa: F401  (imported for its side effect: loaded once, in the server)
from workers.pipeline.geometry.open3d_light import load_open3d

load_open3d()
