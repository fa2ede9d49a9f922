"""The `/viewer` page in a real browser: Debian's Chromium (headless, WebGL on SwiftShader) driven by
`playwright-core` (`tools/viewer/check.mjs`) against a running `citytherm serve` with a model and a
textured job (real PostGIS). The page must draw the model with its thermal textures (pixel checks
on screenshots: the textured facades are not blank, the colour on screen at a known facade point is
the colour-map colour of that point's texel, and the page's colour scale gives the same colour), and
a click on that point must show the surface's gml:id and temperatures, its figures and anomalies
from the Features API, beside the jobs list.

Missing Chromium, node, the npm packages (`tools/viewer/`) or the three.js modules of the page:
the test fails under CI (`CI` set) and is skipped locally, saying what to install.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from db.results_import import import_results
from db.tiles3d.glb import accessor_array, view_bytes
from services.api.routes_viewer import INSTALL_COMMAND, missing_vendor_file
from tests.integration.conftest import ready_api_model
from tests.unit.test_tiles3d_support import glb_ecef, make_textured_results

pytestmark = [pytest.mark.integration, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
TOOLS = REPO / "tools" / "viewer"
CHROMIUM = os.environ.get("CITYTHERM_CHROMIUM", "/usr/bin/chromium")
BACKGROUND = np.array([223, 227, 232])  # the page's scene background, #dfe3e8
ZERO_C_K = 273.15
#: the camera's distance from the known point: a texel (0.2 m) spans some 40 pixels, drawn as it is
FOCUS_DISTANCE_M = 4.0


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def require_browser() -> str:
    """node's path, or fail (CI) / skip (locally) naming what is missing."""
    node = shutil.which("node")
    reason = None
    if node is None:
        reason = "node is not installed (Debian: apt-get install nodejs npm)"
    elif not Path(CHROMIUM).is_file():
        reason = f"Chromium is not installed at {CHROMIUM} (Debian: apt-get install chromium)"
    elif not (TOOLS / "node_modules" / "playwright-core" / "package.json").is_file():
        reason = f"playwright-core is not installed: cd {TOOLS} && npm ci"
    elif (missing := missing_vendor_file()) is not None:
        reason = f"the viewer's three.js modules are not installed ({missing}): {INSTALL_COMMAND}"
    if reason is not None:
        if _in_ci():
            pytest.fail(f"the viewer test needs a browser under CI: {reason}")
        pytest.skip(reason)
    return str(node)


@pytest.fixture(scope="module")
def node() -> str | None:
    """node's path, with Chromium and the npm packages checked before the database work (skips
    locally); None under CI, where the test itself fails when one is missing."""
    return None if _in_ci() else require_browser()


@pytest.fixture(scope="module")
def textured_model(db_engine, tmp_path_factory):
    """The bundled Berlin model as a ready API model with a job's textures: (API model id, name)."""
    results = make_textured_results(tmp_path_factory.mktemp("viewer-job"))
    api_id, model_id = ready_api_model(db_engine, "viewer-berlin")
    import_results(db_engine, results, model=model_id)
    return api_id, "viewer-berlin"


@pytest.fixture(scope="module")
def server(api_server_factory):
    return api_server_factory()


@dataclass(frozen=True)
class KnownPoint:
    """The centre of a display texel on a textured wall, with the texel's colour and temperature."""

    surface: str
    building: str
    mean_k: float
    ecef: np.ndarray  # (3,) metres
    colour: np.ndarray  # (3,) RGB of the display texel
    kelvin: float  # the temperature of the value texel


def _strings(doc: dict, blob: bytes, prop: dict) -> list[str]:
    data = view_bytes(doc, blob, prop["values"])
    offsets = np.frombuffer(view_bytes(doc, blob, prop["stringOffsets"]), dtype=np.uint32)
    return [data[a:b].decode() for a, b in itertools.pairwise(offsets)]


def _image(doc: dict, blob: bytes, texture: int) -> np.ndarray:
    """A texture's image as `(H, W, 3)` uint8 RGB."""
    view = doc["images"][doc["textures"][texture]["source"]]["bufferView"]
    bgr = cv2.imdecode(np.frombuffer(view_bytes(doc, blob, view), np.uint8), cv2.IMREAD_COLOR)
    return bgr[..., ::-1]


def _texel_centres(uv: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Texel centres inside a uv triangle `(3, 2)` (not near its edges) of an image of `size`
    (height, width): their `(n, 2)` texel indexes (x, y) and `(n, 3)` barycentric weights."""
    h, w = size
    lo = np.floor(uv.min(axis=0) * [w, h]).astype(int)
    hi = np.ceil(uv.max(axis=0) * [w, h]).astype(int)
    xs, ys = np.meshgrid(np.arange(max(lo[0], 0), min(hi[0], w)), np.arange(max(lo[1], 0), min(hi[1], h)))
    ij = np.stack([xs.ravel(), ys.ravel()], axis=1)
    centres = (ij + 0.5) / [w, h]
    m = np.stack([uv[1] - uv[0], uv[2] - uv[0]], axis=1)  # (2, 2): uv = uv0 + m @ (s, t)
    if abs(np.linalg.det(m)) < 1e-12:
        return ij[:0], np.zeros((0, 3))
    st = np.linalg.solve(m, (centres - uv[0]).T).T
    bary = np.column_stack([1 - st.sum(axis=1), st])
    inside = (bary > 0.02).all(axis=1)
    return ij[inside], bary[inside]


def known_point(tileset: dict, folder: Path) -> KnownPoint:
    """The observed texel nearest the middle of the largest textured wall of the GLBs in `folder`:
    its centre in ECEF, its display colour and its temperature."""
    best: tuple[float, KnownPoint] | None = None
    for doc, blob, ecef in glb_ecef(tileset, folder).values():
        meta = doc["extensions"]["EXT_structural_metadata"]
        table = meta["propertyTables"][0]["properties"]
        surfaces = _strings(doc, blob, table["surface"])
        buildings = _strings(doc, blob, table["building"])
        classes = _strings(doc, blob, table["surfaceClass"])
        means = np.frombuffer(view_bytes(doc, blob, table["meanTemperature"]["values"]), np.float32)
        thermal = meta["schema"]["classes"]["thermal"]["properties"]["temperature"]
        for prim in doc["meshes"][0]["primitives"]:
            tex = doc["materials"][prim["material"]]["pbrMetallicRoughness"].get("baseColorTexture")
            if tex is None:
                continue
            display = _image(doc, blob, tex["index"])
            k = prim["extensions"]["EXT_structural_metadata"]["propertyTextures"][0]
            value = _image(doc, blob, meta["propertyTextures"][k]["properties"]["temperature"]["index"])
            dn = value[..., 0].astype(int) + 256 * value[..., 1].astype(int)
            tris = accessor_array(doc, blob, prim["indices"]).reshape(-1, 3)
            feature = accessor_array(doc, blob, prim["attributes"]["_FEATURE_ID_0"]).astype(int)
            uv = accessor_array(doc, blob, prim["attributes"]["TEXCOORD_0"]).astype(np.float64)
            for f in np.unique(feature[tris[:, 0]]):
                own = tris[feature[tris[:, 0]] == f]
                a, b, c = ecef[own[:, 0]], ecef[own[:, 1]], ecef[own[:, 2]]
                area = float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2)
                if classes[f] != "WallSurface" or means[f] < 0 or (best is not None and area <= best[0]):
                    continue
                middle = np.concatenate([a, b, c]).mean(axis=0)
                found: tuple[float, KnownPoint] | None = None
                for t in own:
                    ij, bary = _texel_centres(uv[t], display.shape[:2])
                    pts = bary @ ecef[t]
                    d = np.linalg.norm(pts - middle, axis=1)
                    d[dn[ij[:, 1], ij[:, 0]] == 0] = np.inf  # not observed
                    n = int(np.argmin(d)) if len(d) else -1
                    if n < 0 or not np.isfinite(d[n]) or (found is not None and d[n] >= found[0]):
                        continue
                    x, y = ij[n]
                    kelvin = thermal["offset"] + thermal["scale"] * dn[y, x] / 65535
                    found = (float(d[n]), KnownPoint(surfaces[f], buildings[f], float(means[f]), pts[n],
                                                     display[y, x].astype(int), kelvin))  # fmt: skip
                if found is not None:
                    best = (area, found[1])
    assert best is not None, "no textured wall with an observed texel"
    return best[1]


def _download(client: Any, api_id: int, folder: Path) -> dict:
    """The model's tileset and GLBs from the API into `folder`; the tileset JSON."""
    doc = client.get(f"/models/{api_id}/3dtiles/tileset.json").raise_for_status().json()
    stack = [doc["root"]]
    while stack:
        tile = stack.pop()
        stack += tile.get("children", [])
        if "content" in tile:
            uri = tile["content"]["uri"]
            (folder / uri).parent.mkdir(parents=True, exist_ok=True)
            glb = client.get(f"/models/{api_id}/3dtiles/{uri}").raise_for_status()
            (folder / uri).write_bytes(glb.content)
    return doc


def inferno(kelvin: float, lo: float, hi: float) -> np.ndarray:
    """The display colour (RGB) of a temperature, as docs/3dtiles.md defines it."""
    i = int(np.clip(np.floor((kelvin - lo) / (hi - lo) * 254 + 1), 1, 255))
    return cv2.applyColorMap(np.array([[i]], np.uint8), cv2.COLORMAP_INFERNO)[0, 0, ::-1].astype(int)


def _region(png: Path, rect: dict) -> np.ndarray:
    """The pixels of a page screenshot inside a client rect: `(H, W, 3)` int RGB."""
    img = cv2.imread(str(png), cv2.IMREAD_COLOR)[..., ::-1].astype(int)
    x0, y0 = round(rect["x"]), round(rect["y"])
    return img[y0 : y0 + round(rect["height"]), x0 : x0 + round(rect["width"])]


def test_the_viewer_draws_the_model_and_shows_a_clicked_facade(node, server, textured_model, tmp_path):
    node = node or require_browser()
    api_id, _ = textured_model
    with server.client("read") as client:
        tileset = _download(client, api_id, tmp_path)
    lo, hi = tileset["asset"]["extras"]["citytherm"]["display"]["range"]
    known = known_point(tileset, tmp_path)
    assert np.array_equal(known.colour, inferno(known.kelvin, lo, hi))  # the texture follows the scale
    shots = tmp_path / "shots"
    shots.mkdir()
    args = {
        "url": f"{server.base}/viewer?model={api_id}&key={server.keys['read']}",
        "surface": known.surface,
        "point": known.ecef.tolist(),
        "distance": FOCUS_DISTANCE_M,
        "values": [known.kelvin - ZERO_C_K, lo - ZERO_C_K, hi - ZERO_C_K],
        "out": str(shots),
    }
    env = {**os.environ, "CHROMIUM": CHROMIUM}
    cmd = [node, str(TOOLS / "check.mjs"), json.dumps(args)]
    run = subprocess.run(cmd, cwd=TOOLS, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout)
    assert got["state"] == "ready", got["message"]
    assert got["console"] == [], got["console"]

    # the overview: the textured facades are drawn (colour-mapped pixels, many colours), not blank
    view = _region(shots / "overview.png", got["canvas"])
    legend, canvas = got["legend"], got["canvas"]  # the colour scale is an overlay, not the model
    view[: round(legend["bottom"] - canvas["y"]), : round(legend["right"] - canvas["x"])] = BACKGROUND
    pixels = view.reshape(-1, 3)
    drawn = np.abs(pixels - BACKGROUND).max(axis=1) > 12
    colourful = pixels.max(axis=1) - pixels.min(axis=1) > 60  # inferno, not the grey of untextured walls
    assert drawn.mean() > 0.2, drawn.mean()
    assert colourful.mean() > 0.03, colourful.mean()
    assert len(np.unique(pixels[colourful] // 8, axis=0)) > 30  # a texture, not one flat colour

    # the known point: on screen the colour of its texel, which is the page's colour-scale colour
    assert got["framed"] is True and got["point"]["inFront"]
    x, y = round(got["point"]["x"]), round(got["point"]["y"])
    shot = _region(shots / "facade.png", {"x": x - 1, "y": y - 1, "width": 3, "height": 3})
    on_screen = np.median(shot.reshape(-1, 3), axis=0)
    assert np.abs(on_screen - known.colour).max() <= 4, (on_screen, known.colour)
    assert got["colours"][0] == known.colour.tolist()
    assert got["colours"][1:] == [inferno(lo, lo, hi).tolist(), inferno(hi, lo, hi).tolist()]

    # the click: the surface's ids and temperatures, its figures and anomalies, the jobs
    figures = got["figures"]
    assert known.surface in figures and known.building in figures and "WallSurface" in figures
    assert f"{known.mean_k - ZERO_C_K:.1f} °C" in figures
    assert f"At this point\n{known.kelvin - ZERO_C_K:.1f} °C" in figures
    assert "Median" in got["facade"] and "°C" in got["facade"]
    assert got["anomalies"].strip() and "loading" not in got["anomalies"]
    assert "successful" in got["jobs"] and "100 %" in got["jobs"]
    off = np.abs(on_screen - known.colour).max()
    shares = f"drawn {drawn.mean():.2f}, colourful {colourful.mean():.3f}"
    print(f"viewer: loaded in {got['loadMs']} ms, {shares}, texel colour off by {off:.0f}")
