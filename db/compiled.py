"""The switch of the optional compiled parts of the import (setup.py builds them with `make
install`): the CityGML geometry walk (`db.citygml._walk`, used by `building_read`) and the float
texts of the COPY rows (`db._fmt`, used by `import_rows` and `surface_checks`).

Each user imports its compiled module itself (a plain `import`, so the import graph shows it) and
falls back to its Python code when the module is not built or `OFF`; the rows are the same.
"""

from __future__ import annotations

import os

__all__ = ["OFF"]

#: True when `CITYTHERM_NO_COMPILED=1`: every caller uses its Python code (A/B runs)
OFF = os.environ.get("CITYTHERM_NO_COMPILED", "") == "1"
