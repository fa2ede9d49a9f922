"""Open3D without the import cost of its visualisation package.

`import open3d` (0.20) imports `open3d.visualization`, which imports `draw_plotly` and with it
dash and plotly: about 0.55 of the 0.9 CPU seconds of the import, paid by every process that
casts rays (the job's process and the pool's fork server), for a package the pipeline never
uses. `load_open3d()` imports Open3D with a stand-in for `open3d.visualization` that imports
the real package on first use of any of its names, so nothing changes for a caller that does
use it (`open3d.visualization.draw_plotly` still works, at the old cost, when first touched).
"""

from __future__ import annotations

import sys
import types
from typing import Any

_VIS = "open3d.visualization"


class _LazyVisualization(types.ModuleType):
    """Stand-in for `open3d.visualization` until one of its names is used: then the real
    package is imported, takes the stand-in's place (in `sys.modules` and on `open3d`) and
    answers."""

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") and name.endswith("__"):
            raise AttributeError(name)
        return getattr(_real_visualization(), name)


def _real_visualization() -> types.ModuleType:
    """Import the real `open3d.visualization` in place of the stand-in."""
    open3d = sys.modules["open3d"]
    if isinstance(sys.modules.get(_VIS), _LazyVisualization):
        del sys.modules[_VIS]
    import open3d.visualization as real  # the import sets `open3d.visualization` to it

    open3d.visualization = real  # type: ignore[attr-defined]
    return real


def load_open3d() -> Any:
    """The `open3d` module, imported (the first time in the process) with its visualisation
    package deferred (`_LazyVisualization`); an `open3d` imported before is returned as it is."""
    loaded = sys.modules.get("open3d")
    if loaded is not None:
        return loaded
    stub = sys.modules.setdefault(_VIS, _LazyVisualization(_VIS))
    import open3d

    if isinstance(stub, _LazyVisualization) and not hasattr(open3d, "visualization"):
        open3d.visualization = stub  # `import a.b` found in sys.modules binds no attribute
    return open3d
