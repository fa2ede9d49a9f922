"""The units' results kept on the shared storage for the finish task (issue 14's speed-up): each
unit task writes its building's tiles and its result without pixels in the transaction that
stores the result in PostGIS (before its commit), so that the finish, which runs alone once all
units are final, only gathers them instead of loading every result back from PostGIS and
encoding every tile again.

In: a job id, a building gml id, the unit's `BuildingResult` (tiles with pixels) and the storage
directory. Out, under `jobs/<job id>/kept/` (`service_storage` layout):

```
kept/textures/<tile>.png   the unit's 16-bit tiles, as `db.results_folder.write.write_tile` names them
kept/<safe name>.pkl       the result without pixels (`workers.run.without_pixels`), written last
```

The pickle is written last and atomically: when it exists, the unit's tiles are complete. Only
the kept results of units PostGIS records `successful` are used; a delivery whose commit failed
leaves files that the next delivery of the unit writes again alike (a unit's result depends on
its payload alone), and a unit that is final is never run again. A unit task that kept nothing
(a storage error, logged) leaves no pickle: the finish then loads that building from PostGIS and
writes its tiles itself (`kept_result` None), as it did for every building before. A dismissal
waits for the transaction (the job row is locked `FOR SHARE`), then removes the folder.
"""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from pathlib import Path

from db.results_folder.write import write_tile
from workers import service_storage as storage
from workers.pipeline.results import BuildingResult
from workers.run import without_pixels
from workers.service_process import job_dir

__all__ = ["keep_result", "kept_dir", "kept_result"]

log = logging.getLogger(__name__)


def kept_dir(job_id: uuid.UUID) -> Path:
    """`jobs/<job id>/kept/`: the units' tiles and results without pixels."""
    return job_dir(job_id) / "kept"


def _pickle_path(job_id: uuid.UUID, gml_id: str) -> Path:
    return kept_dir(job_id) / f"{storage.safe_name(gml_id)}.pkl"


def keep_result(job_id: uuid.UUID, result: BuildingResult) -> bool:
    """Write `result`'s tiles and the result without pixels (module docstring). Best effort: a
    storage error is logged and leaves no pickle (the finish then reads PostGIS). Returns True
    when both were written."""
    try:
        out = kept_dir(job_id)
        for tile in result.tiles:
            write_tile(out, tile)
        storage.write_pickle(_pickle_path(job_id, result.building_id), without_pixels(result))
        return True
    except Exception as exc:  # the result is in PostGIS already: the finish falls back to it
        log.warning("job %s: keeping the result of %s failed: %s", job_id, result.building_id, exc)
        _pickle_path(job_id, result.building_id).unlink(missing_ok=True)
        return False


def kept_result(job_id: uuid.UUID, gml_id: str, out: Path) -> BuildingResult | None:
    """Building `gml_id`'s kept result without pixels, its tiles linked (or copied) into the
    results folder `out`; None when the unit kept nothing complete (module docstring)."""
    path = _pickle_path(job_id, gml_id)
    try:
        result: BuildingResult = storage.read_pickle(path)
    except (FileNotFoundError, EOFError):
        return None
    src = kept_dir(job_id)
    if not all((src / tile.name).is_file() for tile in result.tiles):
        return None
    for tile in result.tiles:
        dest = out / tile.name
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(src / tile.name, dest)
        except OSError:  # a file system without hard links
            shutil.copyfile(src / tile.name, dest)
    return result
