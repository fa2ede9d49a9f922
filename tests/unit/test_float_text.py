"""The compiled float texts of the import's rows (`db/_fmt.pyx`, Ryu in `db/_ryu/pyrepr64.h`)
against Python's `repr`: random bit patterns over every exponent (subnormals included), random
decimals, rounded values, integers, powers of 2 and 10 and the layout's edges (1e16, 1e-4 / 1e-5,
-0.0); and the COPY / JSON fields made from them against the per-value formulation.

The extension must be built (`make install`): these tests fail, not skip, when it is missing."""

from __future__ import annotations

import numpy as np
import pytest

from db import import_rows, surface_checks

RNG_SEED = 20261126


@pytest.fixture(scope="module")
def fmt():
    assert import_rows._fmt is not None, "db/_fmt.pyx is not built: run `make install`"
    return import_rows._fmt


def _samples() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(RNG_SEED)
    edges = [
        5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, 1e16, 1e15, 9999999999999998.0,
        9007199254740991.0, 9007199254740993.0, 1e-4, 1e-5, 0.0001, 0.00011, 0.1, 0.3, 1 / 3,
        123456789012345680.0, 1e22, 1e23, 0.0, -0.0, 1.0, 100.0, 5e-5, 2.5, 0.5,
    ]  # fmt: skip
    powers = [10.0**k for k in range(-323, 309)] + [2.0**k for k in range(-1074, 1024)]
    values = {
        "bit patterns": rng.integers(0, 2**63, 500_000, dtype=np.uint64).view(np.float64),
        "decimals": rng.normal(0, 1e3, 200_000),
        "rounded": np.round(rng.uniform(-1e6, 1e6, 200_000), 3),
        "integers": np.arange(-50_000, 50_000, dtype=np.float64),
        "powers and edges": np.array(powers + edges),
    }
    return {k: np.concatenate([v, -v]) for k, v in values.items()}


@pytest.mark.parametrize("name", list(_samples()))
def test_texts_are_repr(fmt, name: str) -> None:
    values = _samples()[name]
    assert fmt.repr_texts(values) == list(map(repr, values.tolist()))
    # most values are formatted by Ryu itself, not handed back to repr
    assert fmt.fast_share(values) > 0.98


def test_special_values_are_repr(fmt) -> None:
    values = np.array([np.nan, np.inf, -np.inf, -0.0, 0.0])
    assert fmt.repr_texts(values) == ["nan", "inf", "-inf", "-0.0", "0.0"]


def test_fields_match_per_value_formatting(fmt, monkeypatch: pytest.MonkeyPatch) -> None:
    """`_floats`, the normals' arrays and the checks' `_nums`, compiled and Python, equal."""
    rng = np.random.default_rng(RNG_SEED)
    special = [np.nan, np.inf, -np.inf, -0.0, 0.0, 5e-324, 1e308, 3.0, -7.25, 0.1]
    values = np.concatenate([special, rng.normal(0, 1e3, 290)])
    rng.shuffle(values)
    normal = values.reshape(-1, 3)
    compiled = (import_rows._floats(values), surface_checks._nums(values), fmt.vector_texts(normal, "\\N"))
    monkeypatch.setattr(import_rows, "_fmt", None)
    monkeypatch.setattr(surface_checks, "_fmt", None)
    python = (import_rows._floats(values), surface_checks._nums(values))
    expect_normals = [
        f"{{{a!r},{b!r},{c!r}}}" if a == a and b == b and c == c else "\\N" for a, b, c in normal.tolist()
    ]
    assert compiled[:2] == python
    assert python[0] == [repr(v) if v == v else "\\N" for v in values.tolist()]
    assert python[1] == [repr(v) if np.isfinite(v) else "null" for v in values.tolist()]
    assert compiled[2] == expect_normals and "\\N" in expect_normals
