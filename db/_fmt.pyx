# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False
"""Compiled text of floats for the import's COPY rows: `repr` of each double (shortest
round-trip decimals in Python's layout) through Ryu (`db/_ryu/pyrepr64.h`), about 10 times faster
than `repr`; the values Ryu's fast path does not settle (exact ties and interval bounds, ~0.7 %),
NaN and infinities are formatted by Python's `repr` itself. The same texts as `repr`, checked
against it over millions of doubles in tests/unit/test_float_text.py.

In: float64 arrays. Out: lists of str.
"""

from cpython.unicode cimport PyUnicode_DecodeASCII
from libc.math cimport isinf

import numpy as np

cdef extern from "pyrepr64.h":
    int py_repr64(double f, char* out) nogil


cdef inline str _text(double v, char* buf):
    cdef int k = py_repr64(v, buf)
    if k:
        return PyUnicode_DecodeASCII(buf, k, NULL)
    return repr(v)


def float_texts(values: object, nan: str, nonfinite: object = None) -> list:
    """`repr` of each value of a float64 array (flattened); `nan` for NaN, and `nonfinite` (if
    not None) for NaN and the infinities."""
    cdef const double[::1] v = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
    cdef Py_ssize_t i, n = v.shape[0]
    cdef char buf[40]
    cdef double x
    out = [None] * n
    for i in range(n):
        x = v[i]
        if x != x:
            out[i] = nan if nonfinite is None else nonfinite
        elif nonfinite is not None and isinf(x):
            out[i] = nonfinite
        else:
            out[i] = _text(x, buf)
    return out


def vector_texts(rows: object, null: str) -> list:
    """`{x,y,z}` (`repr` of each) per row of a float64 array `(P, 3)`; `null` for a row with a NaN."""
    cdef const double[:, ::1] v = np.ascontiguousarray(rows, dtype=np.float64).reshape(-1, 3)
    cdef Py_ssize_t i, n = v.shape[0]
    cdef char buf[40]
    out = [None] * n
    for i in range(n):
        if v[i, 0] != v[i, 0] or v[i, 1] != v[i, 1] or v[i, 2] != v[i, 2]:
            out[i] = null
        else:
            out[i] = "{" + _text(v[i, 0], buf) + "," + _text(v[i, 1], buf) + "," + _text(v[i, 2], buf) + "}"
    return out


def repr_texts(values: object) -> list:
    """`repr` of each value (NaN and infinities included), for tests."""
    cdef const double[::1] v = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
    cdef Py_ssize_t i, n = v.shape[0]
    cdef char buf[40]
    return [_text(v[i], buf) for i in range(n)]


def fast_share(values: object) -> float:
    """Fraction of the values formatted by Ryu (not handed back to `repr`), for tests."""
    cdef const double[::1] v = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
    cdef Py_ssize_t i, n = v.shape[0], k = 0
    cdef char buf[40]
    for i in range(n):
        if py_repr64(v[i], buf):
            k += 1
    return k / n if n else 0.0
