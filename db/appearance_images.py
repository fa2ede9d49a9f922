"""Texture images of imported appearances: files next to the CityGML file -> `tex_image` rows.

In: the ids of freshly written appearances and the folder of the CityGML file. Out: one
`tex_image` row (bytes, MIME type, size, bit depth, sha256) per distinct image URI of each
appearance whose file exists, linked from its `surface_data` rows. Only relative URIs that stay
inside the folder are read (a file's `imageURI` never makes the importer read elsewhere); missing
or undecodable images are left as URIs only.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path, PurePosixPath

import numpy as np
from sqlalchemy import Connection, text

from db.ops import copy_rows

__all__ = ["store_appearance_images"]

_MIME = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".tif": "image/tiff",
         ".tiff": "image/tiff", ".gif": "image/gif", ".bmp": "image/bmp"}  # fmt: skip
COLUMNS = ("appearance_id", "uri", "mime_type", "image", "width", "height", "bit_depth", "sha256")


def _inside(folder: Path, uri: str) -> Path | None:
    """The file `uri` names relative to `folder`, or None when it is absolute, a URL, escapes the
    folder or does not exist."""
    p = PurePosixPath(uri.replace("\\", "/"))
    if p.is_absolute() or ":" in uri or ".." in p.parts or not p.parts:
        return None
    path = (folder / Path(*p.parts)).resolve()
    try:
        path.relative_to(folder.resolve())
    except ValueError:
        return None
    return path if path.is_file() else None


def store_appearance_images(conn: Connection, appearance_ids: Sequence[int], folder: Path) -> int:
    """Store the image files of the appearances' textures found under `folder`; returns how many."""
    if not appearance_ids:
        return 0
    wanted = conn.execute(
        text(
            "SELECT DISTINCT appearance_id, image_uri FROM surface_data "
            "WHERE appearance_id = ANY(:a) AND image_uri IS NOT NULL"
        ),
        {"a": list(appearance_ids)},
    ).all()
    import cv2  # here, not at module level: most imports have no texture images to check

    rows = []
    for aid, uri in wanted:
        path = _inside(folder, uri)
        if path is None:
            continue
        data = path.read_bytes()
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            continue
        h, w = img.shape[:2]
        mime = _MIME.get(path.suffix.lower(), "application/octet-stream")
        rows.append((aid, uri, mime, data, w, h, 8 * img.dtype.itemsize, hashlib.sha256(data).hexdigest()))
    if rows:
        copy_rows(conn, "tex_image", COLUMNS, rows)
        conn.execute(
            text(
                "UPDATE surface_data sd SET tex_image_id = ti.id FROM tex_image ti "
                "WHERE sd.appearance_id = ANY(:a) AND ti.appearance_id = sd.appearance_id "
                "AND ti.uri = sd.image_uri"
            ),
            {"a": list(appearance_ids)},
        )
    return len(rows)
