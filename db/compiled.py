"""The optional compiled parts of the import (setup.py builds them with `make install`): the
CityGML geometry walk (`db.citygml._walk`, imported by `building_read` itself, whose package it
is part of) and the float texts of the COPY rows (`db._fmt`: `fmt` here, used by `import_rows` and
`surface_checks`). Each is None when not built or `OFF`; the Python code then gives the same rows.
"""

from __future__ import annotations

import os
from types import ModuleType

__all__ = ["OFF", "fmt"]

#: True when `CITYTHERM_NO_COMPILED=1`: every caller uses its Python code (A/B runs)
OFF = os.environ.get("CITYTHERM_NO_COMPILED", "") == "1"

fmt: ModuleType | None
try:
    from db import _fmt as fmt
except ImportError:  # not built (or for another Python)
    fmt = None
if OFF:
    fmt = None
