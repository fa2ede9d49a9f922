"""Options of a CityGML import (`db.importer.import_citygml`), in a module of their own that
imports nothing heavy: the command line reads them, and starts the reader processes
(`db.import_stream.prestart`), before it loads the database layer.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from os import PathLike

__all__ = ["ImportOptions"]


@dataclass(frozen=True)
class ImportOptions:
    """Options of `import_citygml`.

    Attributes:
        batch_size: top-level buildings per COPY batch (all batches share one transaction).
        checks: geometry checks stored per surface: "fast" (vectorised over the batch: vertex
            count, planarity, area, unclosed rings), "full" (`db.citygml.checks.check_building`,
            adding self-intersection and outward wall normals; about 20 ms per building) or "none".
        huge_tree: passed to the reader (lift libxml2 limits for unusual files).
        parallel_read: parse the file in a separate reader process while this one writes (None:
            for files larger than `parallel_above_bytes`).
        split_above_bytes: a file read in parallel that is at least this large is parsed by two
            reader processes, one per part (`db.import_stream`; the same rows in the same order);
            None: always one reader process.
        split_at: where a split file is cut, as a fraction of its size (at the next
            `cityObjectMember`): the first reader's part is streamed to the database while the
            second reader parses the rest into a temporary file, written after the first part.
            The database writes the second part alone once the readers are done, so a first
            part somewhat larger than half keeps both cores busy longer (`db.import_split`).
        import_images: store the image files of the file's textures that lie in its folder.
        crs: the CRS of the file's coordinates (e.g. `EPSG:25832`) when the file names none, or
            to override what it names. The geometries are stored in the database SRID.
        own_links_unchecked: skip the foreign-key checks of the copied rows (each links to a row
            of this import, by ids it reserved; `session_replication_role = replica` until the
            final step) where the role may and the schema has no trigger of its own.
    """

    batch_size: int = 250
    checks: str = "fast"
    huge_tree: bool = False
    parallel_read: bool | None = None
    parallel_above_bytes: int = 16 * 1024**2
    split_above_bytes: int | None = 32 * 1024**2
    split_at: float = 0.5
    import_images: bool = True
    crs: str | None = None
    own_links_unchecked: bool = True

    def reads_in_parallel(self, path: str | PathLike[str]) -> bool:
        """True when the file `path` is parsed in reader processes (`parallel_read`, else by size)."""
        if self.parallel_read is not None:
            return self.parallel_read
        return os.stat(path).st_size > self.parallel_above_bytes
