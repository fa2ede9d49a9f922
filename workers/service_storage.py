"""The service's files under the storage directory (`docs/service.md`, Storage layout): job
folders, unit payloads, atomic writes and the results zip. Pure file handling, no database.

In: the storage directory (`Settings.storage_dir`), job ids, gml ids, picklable objects. Out:
paths and files:

```
jobs/<job id>/units/<safe name>.pkl   a planned `BuildingUnit` (pickle)
jobs/<job id>/prepared.pkl            what the prepare task keeps for finish
jobs/<job id>/priors.pkl              manifest-only prior pose per frame index (`frame_pose`)
jobs/<job id>/kept/                   the units' tiles and results without pixels, for finish
jobs/<job id>/results/                the results folder; results.zip: the same, zipped
```

Every file is written through a temporary file in the same folder and `os.replace`, so a reader
(or a task delivered again after its worker died) sees the old file or the whole new one.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import re
import uuid
import zipfile
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

__all__ = [
    "job_dir",
    "read_pickle",
    "safe_name",
    "storage_path",
    "unit_path",
    "write_atomic",
    "write_pickle",
    "write_pickles",
    "zip_folder",
]


def safe_name(gml_id: str) -> str:
    """A file name for a gml id: itself when it is made of `[A-Za-z0-9._-]` (not starting with a
    dot, at most 120 characters), else the safe characters (others `_`) and a hash of the id, so
    that two ids never share a name.

    >>> safe_name("BLDG_0001"), safe_name("a/b")
    ('BLDG_0001', 'a_b-c14cddc033f6')
    """
    name = re.sub(r"[^A-Za-z0-9._-]", "_", gml_id)
    if name == gml_id and not name.startswith(".") and 0 < len(name) <= 120:
        return name
    return f"{name.lstrip('.')[:100]}-{hashlib.sha256(gml_id.encode('utf-8')).hexdigest()[:12]}"


def storage_path(storage_dir: str | Path, location: str | Path) -> Path:
    """A location as recorded (absolute, or relative to the storage directory) -> a path."""
    p = Path(location)
    return p if p.is_absolute() else Path(storage_dir) / p


def job_dir(storage_dir: str | Path, job_id: uuid.UUID | str) -> Path:
    """`<storage>/jobs/<job id>/` (absolute)."""
    return Path(storage_dir).resolve() / "jobs" / str(uuid.UUID(str(job_id)))


def unit_path(storage_dir: str | Path, job_id: uuid.UUID | str, gml_id: str) -> Path:
    """`<storage>/jobs/<job id>/units/<safe name>.pkl`: a planned unit."""
    return job_dir(storage_dir, job_id) / "units" / f"{safe_name(gml_id)}.pkl"


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` to `path` (folders created) through a temporary file and `os.replace`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{path.name}-{uuid.uuid4().hex}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_pickle(path: Path, obj: Any) -> None:
    """Pickle `obj` into `path`, atomically."""
    write_atomic(path, pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))


def write_pickles(items: Iterable[tuple[Path, Any]], threads: int = 8) -> None:
    """`write_pickle(path, obj)` for each item, `threads` at a time (their writes and `fsync`s,
    which release the GIL, overlap: a job's units are written in a fraction of the time one by
    one takes). Raises the first error."""
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for _ in pool.map(lambda item: write_pickle(*item), items):
            pass


def read_pickle(path: Path) -> Any:
    """What `write_pickle` wrote (files of this service only: pickle runs code)."""
    with open(path, "rb") as f:
        return pickle.load(f)


def zip_folder(folder: Path, dest: Path) -> None:
    """Zip every file under `folder` (names relative to it, sorted) into `dest`, atomically."""
    tmp = dest.with_name(f".tmp-{dest.name}-{uuid.uuid4().hex}")
    try:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
            for p in sorted(folder.rglob("*")):
                if p.is_file():
                    z.write(p, p.relative_to(folder).as_posix())
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)
