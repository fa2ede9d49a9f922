"""The streaming reader's memory does not grow with the file (elements are dropped once read)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.unit.citygml_docs import boundary, building, polygon, square, write_doc

_PEAK = """
import sys
from pathlib import Path
from db.citygml import iter_buildings
n = sum(len(b.polygons) for b in iter_buildings(sys.argv[1]))
hwm = next(l for l in Path('/proc/self/status').read_text().splitlines() if l.startswith('VmHWM:'))
print(n, int(hwm.split()[1]) // 1024)
"""


def _doc(tmp_path: Path, n: int) -> Path:
    walls = [polygon(None, square(i, 0, 0)) for i in range(8)]
    one = [building(f"B{k}", boundary("WallSurface", f"W{k}", *walls)) for k in range(n)]
    return write_doc(tmp_path, "".join(one), name=f"n{n}.gml")


def _peak_mb(path: Path) -> tuple[int, int]:
    repo = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, "-c", _PEAK, str(path)], capture_output=True, text=True, check=True,
                         cwd=repo).stdout.split()  # fmt: skip
    return int(out[0]), int(out[1])


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc (Linux)")
def test_peak_memory_independent_of_file_size(tmp_path: Path) -> None:
    small, large = _doc(tmp_path, 200), _doc(tmp_path, 8000)
    assert large.stat().st_size > 12e6
    n_small, peak_small = _peak_mb(small)
    n_large, peak_large = _peak_mb(large)
    assert (n_small, n_large) == (1600, 64000)
    # holding the parsed tree of the large file (~14 MB of text, 1.3 M elements) would take >100 MB
    assert peak_large - peak_small < 10, (peak_small, peak_large)
