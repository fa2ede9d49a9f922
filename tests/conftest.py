"""Shared test fixtures: paths to the shared contract data."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("CITYTHERM_SHARED", REPO.parent / "shared"))
DATA = SHARED / "data"
SCHEMAS = SHARED / "schemas"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Folder of the real CityGML samples (`../shared/data`)."""
    assert DATA.is_dir(), f"shared data not found at {DATA} (set CITYTHERM_SHARED)"
    return DATA


@pytest.fixture(scope="session")
def schemas_dir() -> Path:
    """Folder of the CityGML 2.0 schemas (`../shared/schemas`)."""
    assert SCHEMAS.is_dir(), f"schemas not found at {SCHEMAS} (set CITYTHERM_SHARED)"
    return SCHEMAS
