"""The optional compiled parts of the import (setup.py builds them with `make install`): the
CityGML geometry walk (`db.citygml._walk`) and the float texts of the COPY rows (`db._fmt`).

`load(name)` gives the module, or None when it is not built or `CITYTHERM_NO_COMPILED=1` turns the
compiled parts off (A/B runs; the Python code then gives the same rows).
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType

__all__ = ["OFF", "load"]

#: True when `CITYTHERM_NO_COMPILED=1`: every caller uses its Python code
OFF = os.environ.get("CITYTHERM_NO_COMPILED", "") == "1"


def load(name: str) -> ModuleType | None:
    """The compiled module `name`, or None (not built, built for another Python, or turned off)."""
    if OFF:
        return None
    try:
        return importlib.import_module(name)
    except ImportError:
        return None
