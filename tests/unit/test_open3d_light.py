"""`geometry.open3d_light`: Open3D imported without its visualisation package (dash, plotly),
which still answers when used."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

_PROBE = """
import json, sys
from workers.pipeline.geometry.open3d_light import load_open3d
o3d = load_open3d()
light = {"dash": "dash" in sys.modules, "plotly": "plotly" in sys.modules}
import numpy as np
scene = o3d.t.geometry.RaycastingScene()
scene.add_triangles(o3d.core.Tensor(np.array([[0, 0, 5], [1, 0, 5], [0, 1, 5]], np.float32)),
                    o3d.core.Tensor(np.array([[0, 1, 2]], np.uint32)))
ans = scene.cast_rays(o3d.core.Tensor(np.array([[0.2, 0.2, 0, 0, 0, 1]], np.float32)))
import open3d
light["same"] = open3d is o3d and load_open3d() is o3d
light["t_hit"] = float(ans["t_hit"].numpy()[0])
light["draw_plotly"] = callable(o3d.visualization.draw_plotly)
from open3d.visualization import get_plotly_fig
light["from_import"] = callable(get_plotly_fig)
light["real"] = type(sys.modules["open3d.visualization"]).__name__
light["dash_after"] = "dash" in sys.modules
print(json.dumps(light))
"""


def test_open3d_loads_without_dash_and_visualization_still_answers() -> None:
    done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, check=True,
                          cwd=REPO, env=None, timeout=300)  # fmt: skip
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["dash"] is False and got["plotly"] is False  # the light import skipped them
    assert got["same"] is True
    assert abs(got["t_hit"] - 5.0) < 1e-5  # ray casting works
    assert got["draw_plotly"] is True and got["from_import"] is True  # visualization on first use
    assert got["real"] == "module" and got["dash_after"] is True
