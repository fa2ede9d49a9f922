"""The `/viewer` routes without a database (`services/api/routes_viewer.py`): 503 naming the install
command while the three.js modules are missing, the page with a Content-Security-Policy that lets
exactly its import map run, the files under it and nothing outside it; the list of modules the
route checks is the list `tools/viewer/vendor.mjs` copies, and the page's imports are among them.
The page itself in a browser: tests/integration/test_viewer.py."""

from __future__ import annotations

import base64
import hashlib
import re
import shutil
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from services.api import routes_viewer
from services.api.problems import install_problem_handlers

REPO = Path(__file__).resolve().parents[2]


def _client() -> TestClient:
    app = FastAPI()
    install_problem_handlers(app)
    app.include_router(routes_viewer.router)
    return TestClient(app)


@pytest.fixture
def viewer_dir(tmp_path, monkeypatch):
    """A copy of the viewer's own files (no vendor folder) as the package's viewer folder."""
    folder = tmp_path / "viewer"
    folder.mkdir()
    for f in routes_viewer.VIEWER_DIR.iterdir():
        if f.is_file():
            shutil.copy(f, folder / f.name)
    monkeypatch.setattr(routes_viewer, "VIEWER_DIR", folder)
    return folder


def _install_vendor(folder: Path) -> None:
    for f in routes_viewer.VENDOR_FILES:
        (folder / "vendor" / f).parent.mkdir(parents=True, exist_ok=True)
        (folder / "vendor" / f).write_text("export {};\n")


def test_without_the_three_modules_the_viewer_is_503_naming_the_command(viewer_dir):
    client = _client()
    for path in ("/viewer/", "/viewer/vendor/three/build/three.module.js"):
        r = client.get(path)
        assert r.status_code == 503
        assert r.headers["content-type"].startswith("application/problem+json")
        assert "make viewer" in r.json()["detail"] and "npm ci" in r.json()["detail"]
    assert client.get("/viewer/viewer.js").status_code == 200  # the page's own files are there


def test_the_page_and_its_files(viewer_dir):
    _install_vendor(viewer_dir)
    client = _client()
    r = client.get("/viewer?model=3", follow_redirects=False)
    assert r.status_code == 307 and r.headers["location"].endswith("/viewer/?model=3")
    page = client.get("/viewer/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    csp = page.headers["content-security-policy"]
    inline = re.findall(r'<script type="importmap">(.*?)</script>', page.text, flags=re.DOTALL)
    assert len(inline) == 1
    digest = base64.b64encode(hashlib.sha256(inline[0].encode()).digest()).decode()
    assert f"script-src 'self' 'sha256-{digest}';" in csp and "default-src 'self'" in csp
    js = client.get("/viewer/vendor/three/build/three.module.js")
    assert js.status_code == 200 and js.headers["content-type"].startswith("text/javascript")
    for bad in ("/viewer/../app.py", "/viewer/%2e%2e/app.py", "/viewer/nothing.js", "/viewer/index.py"):
        assert client.get(bad).status_code == 404, bad


def test_the_vendored_modules_are_those_vendor_mjs_copies_and_the_page_imports():
    script = (REPO / "tools" / "viewer" / "vendor.mjs").read_text()
    copied = set(re.findall(r'^\s*"((?:build|examples)/[^"]+)"', script, flags=re.MULTILINE))
    assert copied == {f.removeprefix("three/") for f in routes_viewer.VENDOR_FILES}
    page = (REPO / "services" / "api" / "viewer" / "index.html").read_text()
    imports = re.findall(r'"\./vendor/([^"]+)"', page)
    assert "three/build/three.module.js" in imports
    sources = " ".join((REPO / "services/api/viewer" / n).read_text() for n in ("viewer.js", "tiles.js"))
    for addon in re.findall(r'from "three/addons/([^"]+)"', sources):
        assert f"three/examples/jsm/{addon}" in routes_viewer.VENDOR_FILES
