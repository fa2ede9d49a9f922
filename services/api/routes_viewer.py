"""The web viewer: `GET /viewer/` serves a page that shows a city model's newest thermal job in 3D
(three.js, from the model's 3D Tiles), a colour scale in °C, the figures and anomalies of a
clicked facade and the jobs with their progress (`docs/viewer.md`).

Static files only, served from this package (`services/api/viewer/`): `index.html`, `viewer.js`,
`viewer.css` and the three.js modules in `viewer/vendor/`, which `make viewer` copies there from
the npm package (`tools/viewer/`). Without them `/viewer/` answers 503, naming that command. The
files are public (they hold no data); the page sends the API key the user gives it with each data
call (`Authorization: Bearer`). Not in the OpenAPI document: a page, not an API.
"""

from __future__ import annotations

import base64
import hashlib
import re
from functools import lru_cache
from pathlib import Path as FsPath
from typing import Annotated

from fastapi import APIRouter, HTTPException, Path, Request
from fastapi.responses import FileResponse, RedirectResponse

router = APIRouter()

VIEWER_DIR = FsPath(__file__).resolve().parent / "viewer"
#: the three.js modules the page imports (`tools/viewer/vendor.mjs` copies these, and only these)
VENDOR_FILES = (
    "three/build/three.module.js",
    "three/build/three.core.js",
    "three/examples/jsm/loaders/GLTFLoader.js",
    "three/examples/jsm/controls/OrbitControls.js",
    "three/examples/jsm/utils/BufferGeometryUtils.js",
    "three/examples/jsm/utils/SkeletonUtils.js",
)
INSTALL_COMMAND = "make viewer (cd tools/viewer && npm ci && node vendor.mjs)"
MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".txt": "text/plain; charset=utf-8",
}


class ViewerNotInstalled(HTTPException):
    """503: the three.js modules of the viewer are missing from the package."""

    def __init__(self, missing: str) -> None:
        super().__init__(
            503,
            f"the viewer's three.js modules are not installed ({missing} is missing); "
            f"install them with: {INSTALL_COMMAND}",
        )


def missing_vendor_file(folder: FsPath | None = None) -> str | None:
    """The first of `VENDOR_FILES` missing under `<folder>/vendor` (default: the package's viewer
    folder), or None when all are there."""
    vendor = (folder or VIEWER_DIR) / "vendor"
    return next((f"vendor/{f}" for f in VENDOR_FILES if not (vendor / f).is_file()), None)


@lru_cache(maxsize=4)
def content_security_policy(index_html: bytes) -> str:
    """The page's Content-Security-Policy: everything from this origin, and the one inline script
    (the import map) by its SHA-256; images, textures and GLBs also from `blob:` and `data:`
    URLs (GLTFLoader decodes embedded images through them)."""
    scripts = re.findall(rb'<script type="importmap">(.*?)</script>', index_html, flags=re.DOTALL)
    hashes = " ".join(f"'sha256-{base64.b64encode(hashlib.sha256(s).digest()).decode()}'" for s in scripts)
    return (
        f"default-src 'self'; script-src 'self' {hashes}; style-src 'self'; "
        "img-src 'self' blob: data:; connect-src 'self' blob: data:; object-src 'none'; "
        "base-uri 'none'; frame-ancestors 'none'"
    )


@router.get("/viewer", include_in_schema=False)
def viewer_redirect(request: Request) -> RedirectResponse:
    """`/viewer` -> `/viewer/` (with the query), so that the page's relative URLs resolve."""
    query = f"?{request.url.query}" if request.url.query else ""
    return RedirectResponse(f"{request.url.path}/{query}", status_code=307)


@router.get("/viewer/", include_in_schema=False, response_class=FileResponse)
def viewer_page() -> FileResponse:
    """The viewer page (503 while the three.js modules are not installed)."""
    missing = missing_vendor_file(VIEWER_DIR)
    if missing is not None:
        raise ViewerNotInstalled(missing)
    index = VIEWER_DIR / "index.html"
    headers = {
        "Content-Security-Policy": content_security_policy(index.read_bytes()),
        "Cache-Control": "no-cache",
        "X-Content-Type-Options": "nosniff",
        "Referrer-Policy": "no-referrer",
    }
    return FileResponse(index, media_type=MEDIA_TYPES[".html"], headers=headers)


@router.get("/viewer/{path:path}", include_in_schema=False, response_class=FileResponse)
def viewer_file(path: Annotated[str, Path(max_length=300)]) -> FileResponse:
    """A file of the viewer (script, style sheet, three.js module) by its path under the page."""
    try:
        target = (VIEWER_DIR / path).resolve()
        found = VIEWER_DIR in target.parents and target.suffix in MEDIA_TYPES and target.is_file()
    except (ValueError, OSError):  # a NUL byte, a name too long
        found = False
    if not found:
        if path.startswith("vendor/") and missing_vendor_file(VIEWER_DIR) is not None:
            raise ViewerNotInstalled(path)
        raise HTTPException(404, f"no file {path[:200]!r} in the viewer")
    return FileResponse(
        target,
        media_type=MEDIA_TYPES[target.suffix],
        headers={"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"},
    )
